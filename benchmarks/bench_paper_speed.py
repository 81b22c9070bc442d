"""The JAX estimate against the paper's own pixel procedure: faithfulness, then speed (issue 6).

Run from the repository root:

    .venv/bin/python benchmarks/bench_paper_speed.py           # full run (about 6 minutes on 2 cores)
    .venv/bin/python benchmarks/bench_paper_speed.py --quick   # tiny configuration (CI smoke test)

It prints markdown tables ready for benchmarks/RESULTS.md (progress on stderr) and writes
``paper_speed.png`` (time against batch size and against N) and ``paper_speed.json`` (every raw
figure) into ``--out`` (default ``out/paper_speed``, which git ignores). ``--pixel-mm`` and
``--angle-step`` set the reference's resolution; the default 0.1 mm/px is the coarsest at which
its joints agree with the JAX estimate's to within 1 mm (at 0.31 mm/px, the D405's scale at
120 mm, a few per cent of the fingers differ by more).

1. Faithfulness. Random scenes (every kind of object in ``synthetic.shapes`` in turn, 12-40 mm,
   randomly rotated, next to a finger of L 50-54 mm, r = 4 mm, Theta 0.4-0.6 rad: a fifth placed
   anywhere around the finger, the rest across the closed finger's path or just beside its lower
   part, so that all four cases occur; scenes where the open finger comes within r + 0.3 mm of the
   object are redrawn) are estimated by the pixel reference (``paper_pixel.py``) and by
   ``softgrip_jax.estimate`` on the exact ``PolygonSDF``, for N = 2, 10 and 20, with the PCC sweep
   and with the rigid sweep. Reported: case agreement, and the joint differences over the fingers
   whose cases agree. Nothing is asserted.
2. Speed. One scene (a 30 mm circle; the finger bases spread as in bench_estimate.py, so that all
   four cases occur, less those whose open finger already touches the circle): the reference's time per candidate-finger, and ``estimate_batch``'s on the
   scene's 480 x 640 ``SDFGrid`` at 0.31 mm/px (after compilation, best of 3; compilation time is
   the first call minus the best), for N in {2, 10, 20} and batches of 1, 100 and 10,000. The
   reference is a Python loop over candidates, so its time is linear in the batch: the batch of
   10,000 is timed on its first few hundred candidates and extrapolated (the output says so). The
   object's drawing (the reference's counterpart of the SDF) is timed separately. The reference's
   and the JAX estimate's cases and joints on the timed candidates are compared too.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
if str(_HERE.parent) not in sys.path:
    sys.path.insert(1, str(_HERE.parent))

import paper_pixel  # noqa: E402
from softgrip_jax import Geometric

LENGTH_MM = (50.0, 54.0)
THETA_RAD = (0.4, 0.6)
HALF_THICKNESS_MM = 4.0
SPEED_LENGTH_MM, SPEED_THETA_RAD = 52.0, 0.5
CLEARANCE_MM = 0.3  # open finger at least this far from the object beyond r (no initial overlap)


# ----------------------------------------------------------------------------------------------
# Scenes


@dataclass(frozen=True)
class Scene:
    """One finger and one object (mm, rad)."""

    object_name: str
    polygon: np.ndarray  # (V, 2)
    base: np.ndarray  # (2,)
    length: float
    theta: float
    half_thickness: float


def polygon_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance (mm, negative inside) of points (M, 2) to a closed polygon (V, 2)."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    ab = b - a
    ap = points[:, None, :] - a
    t = np.clip(np.sum(ap * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    dist = np.sqrt(np.min(np.sum((ap - t[..., None] * ab) ** 2, -1), axis=1))
    py, px = points[:, None, 1], points[:, None, 0]
    straddles = (a[:, 1] > py) != (b[:, 1] > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0] + (py - a[:, 1]) * ab[:, 0] / ab[:, 1]
    inside = np.sum(straddles & (px < x_cross), axis=1) % 2 == 1
    return np.where(inside, -dist, dist)


def faithfulness_scenes(count: int, seed: int = 0) -> list[Scene]:
    """``count`` random scenes, objects of every kind in ``synthetic.shapes``, none touching
    the open finger."""
    from synthetic.shapes import SHAPES, shape

    rng = np.random.default_rng(seed)
    names = list(SHAPES)
    scenes = []
    while len(scenes) < count:
        name = names[len(scenes) % len(names)]
        size = rng.uniform(12.0, 40.0)
        base = rng.uniform(-5.0, 5.0, 2)
        length, theta = rng.uniform(*LENGTH_MM), rng.uniform(*THETA_RAD)
        outline = shape(name, size, rng.uniform(0.0, 2.0 * math.pi))
        mode = rng.uniform()
        if mode < 0.2:  # anywhere around the finger: mostly no contact
            polygon = outline + base + rng.uniform([-15.0, 5.0], [50.0, 90.0])
        elif mode < 0.6:  # across the closed finger's path (PCC arc of eqs. 2-3, continued past the tip)
            u = rng.uniform(0.25, 1.3)
            a = theta * min(u, 1.0)  # direction of the arc (and of its tangent past the tip)
            on_arc = length * (np.array([1.0 - math.cos(2 * a), math.sin(2 * a)]) / (2 * theta)
                               + max(u - 1.0, 0.0) * np.array([math.sin(2 * theta), math.cos(2 * theta)]))
            inward = np.array([math.cos(2 * a), -math.sin(2 * a)])  # toward the curl's centre
            polygon = outline + base + on_arc + inward * rng.uniform(-0.2, 0.7) * size
        else:  # the object's leftmost point just right of the open finger's lower part: early
            # contact near the tip on the object's left side, where case (c) happens
            leftmost = outline[np.argmin(outline[:, 0])]
            target = base + np.array([HALF_THICKNESS_MM + rng.uniform(0.5, 12.0), rng.uniform(0.5, 1.05) * length])
            polygon = outline + (target - leftmost)
        open_finger = base + np.linspace(0.0, length, 521)[:, None] * np.array([0.0, 1.0])
        if polygon_distance(open_finger, polygon).min() <= HALF_THICKNESS_MM + CLEARANCE_MM:
            continue
        scenes.append(Scene(name, polygon, base, length, theta, HALF_THICKNESS_MM))
    return scenes


# ----------------------------------------------------------------------------------------------
# Both estimators on the faithfulness scenes


def jax_scene_estimates(scenes: list[Scene], n_links: int, sweep: str = "pcc"):
    """``softgrip_jax.estimate`` on each scene's exact ``PolygonSDF``, all scenes in one vmapped call.

    Returns (case (S,), joints (S, N+1, 2), valid (S,)) as numpy.
    """
    import jax
    import jax.numpy as jnp

    from softgrip_jax import ContactConfig, FingerModel, PolygonSDF, estimate

    config = ContactConfig(sweep=sweep)
    v_max = max(s.polygon.shape[0] for s in scenes)
    # Padding repeats the last vertex: zero-length edges change neither distance nor inside test.
    vertices = np.stack([np.concatenate([s.polygon, np.repeat(s.polygon[-1:], v_max - len(s.polygon), 0)])
                         for s in scenes]).astype(np.float32)

    def one(length, theta, r, verts, base):
        return estimate(FingerModel(length, theta, r, n_links), PolygonSDF(verts), base, config, estimator=Geometric())

    column = lambda f: jnp.asarray(np.array([f(s) for s in scenes], np.float32))
    out = jax.jit(jax.vmap(one))(column(lambda s: s.length), column(lambda s: s.theta),
                                 column(lambda s: s.half_thickness), jnp.asarray(vertices),
                                 column(lambda s: s.base))
    return np.asarray(out.case), np.asarray(out.joints), np.asarray(out.valid)


def reference_scene_estimates(scenes: list[Scene], n_links: int, pixel_mm: float, angle_step, sweep: str = "pcc"):
    """The pixel reference on each scene. Returns (case (S,), joints (S, N+1, 2), initial_overlap (S,), s)."""
    cases, joints, overlap = [], [], []
    t0 = time.perf_counter()
    for s in scenes:
        finger = paper_pixel.PixelFinger(s.length, s.theta, s.half_thickness, n_links)
        est = paper_pixel.estimate(s.polygon, s.base, finger, pixel_mm, angle_step, sweep)
        cases.append(est.case)
        joints.append(est.joints)
        overlap.append(est.initial_overlap)
    return np.array(cases), np.array(joints), np.array(overlap), time.perf_counter() - t0


def compare(ref_case, ref_joints, jax_case, jax_joints, usable) -> dict:
    """Case agreement (%) and joint differences (mm, joints 1..N: the bases coincide) over the usable
    fingers."""
    ref_case, jax_case = ref_case[usable], jax_case[usable]
    agree = ref_case == jax_case
    diff = np.linalg.norm(ref_joints[usable][:, 1:] - jax_joints[usable][:, 1:], axis=-1)  # (S, N)
    worst = diff.max(axis=1)
    confusion = np.zeros((4, 4), int)
    np.add.at(confusion, (ref_case, jax_case), 1)
    agreeing = worst[agree]
    return {
        "fingers": int(usable.sum()),
        "case_agreement_pct": 100.0 * float(agree.mean()) if agree.size else float("nan"),
        "joint_diff_mean_mm": float(diff[agree].mean()) if agree.any() else float("nan"),
        "joint_diff_max_mm": float(agreeing.max()) if agree.any() else float("nan"),
        "within_1mm_pct": 100.0 * float((agreeing <= 1.0).mean()) if agree.any() else float("nan"),
        "confusion_ref_rows_jax_cols": confusion.tolist(),
        "cases_jax": np.bincount(jax_case, minlength=4).tolist(),
    }


def faithfulness(scenes, links, sweeps, pixel_mm, angle_step, log) -> list[dict]:
    """Both estimators on every scene for each sweep and N; fingers either one finds already touching
    the object (JAX ``valid`` false or the reference's initial overlap) are left out."""
    rows = []
    for sweep in sweeps:
        for n in links:
            t0 = time.perf_counter()
            jax_case, jax_joints, valid = jax_scene_estimates(scenes, n, sweep)
            t_jax = time.perf_counter() - t0
            ref_case, ref_joints, ref_overlap, t_ref = reference_scene_estimates(scenes, n, pixel_mm, angle_step,
                                                                                sweep)
            usable = valid & ~ref_overlap
            row = {"sweep": sweep, "n_links": n, "scenes": len(scenes), "excluded": int((~usable).sum()),
                   "reference_s": t_ref, "jax_s_with_compile": t_jax,
                   **compare(ref_case, ref_joints, jax_case, jax_joints, usable)}
            rows.append(row)
            log(f"  faithfulness {sweep} N={n}: {row['case_agreement_pct']:.1f} % cases agree, joints "
                f"mean {row['joint_diff_mean_mm']:.3f} / max {row['joint_diff_max_mm']:.3f} mm "
                f"(reference {t_ref:.1f} s)")
    return rows


# ----------------------------------------------------------------------------------------------
# Speed


def speed_scene():
    """The timed scene: a 30 mm circle at the origin, a 480 x 640 grid at 0.31 mm/px around it."""
    from synthetic.shapes import shape

    spacing = 120.0 / 385.0
    origin = (-320 * spacing, -240 * spacing)
    return shape("circle", 30.0), origin, spacing, (480, 640)


def speed_bases(count: int, seed: int = 1) -> np.ndarray:
    """Finger bases (mm) spread as in bench_estimate.py, so that all four cases occur, less those
    whose open finger would already touch the timed 30 mm circle (they would time the collision test,
    not the estimate)."""
    rng = np.random.default_rng(seed)
    clear = 15.0 + HALF_THICKNESS_MM + CLEARANCE_MM
    bases = np.empty((0, 2))
    while len(bases) < count:
        draw = rng.uniform([-60.0, -70.0], [20.0, -10.0], (count, 2))
        # Distance from the circle's centre (the origin) to the open finger, base to base + (0, L).
        nearest_y = np.clip(0.0, draw[:, 1], draw[:, 1] + SPEED_LENGTH_MM)
        keep = np.hypot(draw[:, 0], nearest_y) > clear
        bases = np.concatenate([bases, draw[keep]])
    return bases[:count]


def time_jax(finger, grid, bases, repeats: int) -> tuple[float, float, object]:
    """(best steady time s, compile time s, result) of ``estimate_batch`` on ``bases``."""
    import jax
    import jax.numpy as jnp

    from softgrip_jax import estimate_batch

    bases = jnp.asarray(bases, jnp.float32)
    t0 = time.perf_counter()
    out = jax.block_until_ready(estimate_batch(finger, grid, bases, estimator=Geometric()))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(estimate_batch(finger, grid, bases, estimator=Geometric()))
        times.append(time.perf_counter() - t0)
    best = min(times)
    return best, max(first - best, 0.0), out


def speed(links, batches, ref_sample: int, pixel_mm: float, angle_step, repeats: int, log) -> tuple[list, list]:
    """Times of both estimators on the speed scene (rows per N and batch), and their agreement on the
    candidates the reference was timed on (a row per N)."""
    import jax
    import jax.numpy as jnp

    from softgrip_jax import FingerModel, PolygonSDF, SDFGrid

    polygon, origin, spacing, grid_shape = speed_scene()
    grid = jax.block_until_ready(SDFGrid.sample(PolygonSDF(jnp.asarray(polygon, jnp.float32)), origin,
                                                (spacing, spacing), grid_shape))
    all_bases = speed_bases(max(batches))
    rows, agreement = [], []
    for n in links:
        finger = FingerModel(length=SPEED_LENGTH_MM, theta_entire=SPEED_THETA_RAD, half_thickness=HALF_THICKNESS_MM,
                             n_links=n)
        pfinger = paper_pixel.PixelFinger.like(finger)
        # The reference: the object drawn once (its SDF), then one Python call per candidate.
        t0 = time.perf_counter()
        scene = paper_pixel.PixelScene.around(polygon, all_bases, pfinger, pixel_mm)
        scene.contour(pfinger.half_thickness)
        setup = time.perf_counter() - t0
        single = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            scene.estimate(pfinger, all_bases[0], angle_step)
            single.append(time.perf_counter() - t0)
        # Timed candidate by candidate; batches up to ``sample`` are timed whole, larger ones extrapolated.
        sample = min(max(batches), max(ref_sample, max((b for b in batches if b < max(batches)), default=1)))
        per, ref = [], []
        for base in all_bases[:sample]:
            t0 = time.perf_counter()
            ref.append(scene.estimate(pfinger, base, angle_step))
            per.append(time.perf_counter() - t0)
        per = np.array(per)
        jax_full = None
        for b in batches:
            if b == 1:
                ref_s, extrapolated = min(single), False
            elif b <= sample:
                ref_s, extrapolated = float(per[:b].sum()), False
            else:
                ref_s, extrapolated = float(per.mean() * b), True
            jax_s, compile_s, out = time_jax(finger, grid, all_bases[:b], repeats)
            if b == max(batches):
                jax_full = out
            row = {"n_links": n, "batch": b, "reference_s": ref_s, "reference_extrapolated_from": sample if extrapolated
                   else None, "reference_setup_s": setup, "jax_s": jax_s, "jax_compile_s": compile_s,
                   "reference_per_s": b / ref_s, "jax_per_s": b / jax_s, "ratio": ref_s / jax_s}
            rows.append(row)
            log(f"  speed N={n} batch={b}: reference {ref_s:.3g} s{' (extrapolated)' if extrapolated else ''}, "
                f"JAX {jax_s:.3g} s (compile {compile_s:.1f} s), ratio {row['ratio']:,.0f}")
        # The same timed candidates, both ways.
        valid = np.asarray(jax_full.valid)[:sample] & ~np.array([e.initial_overlap for e in ref])
        a = compare(np.array([e.case for e in ref]), np.array([e.joints for e in ref]),
                    np.asarray(jax_full.case)[:sample], np.asarray(jax_full.joints)[:sample], valid)
        agreement.append({"n_links": n, "candidates": sample, **a})
        log(f"  timed candidates N={n}: {a['case_agreement_pct']:.1f} % cases agree, joints mean "
            f"{a['joint_diff_mean_mm']:.3f} / max {a['joint_diff_max_mm']:.3f} mm")
    return rows, agreement


# ----------------------------------------------------------------------------------------------
# Report


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    links = sorted({r["n_links"] for r in rows})
    batches = sorted({r["batch"] for r in rows})
    colours = dict(zip(links, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.5))
    for n in links:
        rs = sorted((r for r in rows if r["n_links"] == n), key=lambda r: r["batch"])
        b = [r["batch"] for r in rs]
        left.loglog(b, [r["reference_s"] for r in rs], "o--", color=colours[n], label=f"pixel reference, N={n}")
        left.loglog(b, [r["jax_s"] for r in rs], "s-", color=colours[n], label=f"JAX estimate_batch, N={n}")
        guessed = [r for r in rs if r["reference_extrapolated_from"]]
        left.loglog([r["batch"] for r in guessed], [r["reference_s"] for r in guessed], "o", color="white",
                    markeredgecolor=colours[n])
    sampled = sorted({r["reference_extrapolated_from"] for r in rows if r["reference_extrapolated_from"]})
    if sampled:
        left.text(0.02, 0.02, f"open circles: extrapolated from {sampled[0]} candidates", transform=left.transAxes,
                  fontsize=7)
    left.set(xlabel="batch (candidate-fingers)", ylabel="time per batch (s)", title="Time against batch size")
    left.grid(True, which="both", alpha=0.3)
    left.legend(fontsize=7)
    markers = dict(zip(batches, "o^sDv"))
    for b in batches:
        rs = sorted((r for r in rows if r["batch"] == b), key=lambda r: r["n_links"])
        n = [r["n_links"] for r in rs]
        extrapolated = " (extrapolated)" if any(r["reference_extrapolated_from"] for r in rs) else ""
        right.semilogy(n, [r["reference_s"] / b for r in rs], markers[b] + "--", color="tab:red",
                       label=f"pixel reference, batch {b:,}{extrapolated}")
        right.semilogy(n, [r["jax_s"] / b for r in rs], markers[b] + "-", color="tab:blue",
                       label=f"JAX, batch {b:,}")
    right.set(xlabel="N (links)", ylabel="time per candidate-finger (s)", title="Time against N",
              xticks=links)
    right.grid(True, which="both", alpha=0.3)
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def tables(config: dict, faith: list[dict], speed_rows: list[dict], timed: list[dict]) -> str:
    from _machine import describe

    lines = [f"`{config['command']}` on {describe()}; reference at {config['pixel_mm']} mm/px, angle step "
             f"{config['angle_step_text']}; {config['wall_s']:.0f} s wall time", ""]
    lines += [f"Faithfulness: {config['scenes']} random scenes (objects of every kind in synthetic.shapes, "
              "12-40 mm, L 50-54 mm, r = 4 mm, Theta 0.4-0.6 rad); the JAX estimate on the exact PolygonSDF; "
              "joint differences over the fingers whose cases agree (mean and max over joints 1..N, and the "
              "share of fingers whose every joint is within 1 mm).", "",
              "| sweep | N | fingers | cases agree | joints, agreeing cases: mean / max (mm) | within 1 mm | "
              "cases (JAX) none/tip/tip+other/other |",
              "|---|---|---|---|---|---|---|"]
    for r in faith:
        lines.append(f"| {r['sweep']} | {r['n_links']} | {r['fingers']} | {r['case_agreement_pct']:.1f} % | "
                     f"{r['joint_diff_mean_mm']:.3f} / {r['joint_diff_max_mm']:.3f} | {r['within_1mm_pct']:.1f} % | "
                     f"{'/'.join(map(str, r['cases_jax']))} |")
    lines += ["", "Speed: one scene (30 mm circle), finger bases spread so that all cases occur (none touching the "
              "circle when open); the reference per candidate, the object drawn once; JAX `estimate_batch` on a "
              "480 x 640 SDFGrid at 0.31 mm/px, after compilation, best of 3.", "",
              "| N | batch | reference (s) | reference cand.-fingers/s | JAX (s) | JAX cand.-fingers/s | "
              "JAX compile (s) | ratio |",
              "|---|---|---|---|---|---|---|---|"]
    for r in speed_rows:
        star = "*" if r["reference_extrapolated_from"] else ""
        lines.append(f"| {r['n_links']} | {r['batch']:,} | {r['reference_s']:.3g}{star} | {r['reference_per_s']:,.1f} | "
                     f"{r['jax_s']:.3g} | {r['jax_per_s']:,.0f} | {r['jax_compile_s']:.1f} | {r['ratio']:,.0f} |")
    extrapolated = sorted({r["reference_extrapolated_from"] for r in speed_rows if r["reference_extrapolated_from"]})
    if extrapolated:
        lines += ["", f"\\* extrapolated linearly from the reference's time on the first {extrapolated[0]} candidates "
                  "(a per-candidate Python loop)."]
    setup = {r["n_links"]: r["reference_setup_s"] for r in speed_rows}
    lines += ["", "Reference setup (object drawn and dilated once per scene, not in the times above): "
              + ", ".join(f"N={n}: {s:.2f} s" for n, s in setup.items()) + "."]
    lines += ["", "The timed candidates, both ways:", "",
              "| N | candidates | cases agree | joints, agreeing cases: mean / max (mm) | within 1 mm | "
              "cases (JAX) none/tip/tip+other/other |",
              "|---|---|---|---|---|---|"]
    for r in timed:
        lines.append(f"| {r['n_links']} | {r['fingers']} | {r['case_agreement_pct']:.1f} % | "
                     f"{r['joint_diff_mean_mm']:.3f} / {r['joint_diff_max_mm']:.3f} | {r['within_1mm_pct']:.1f} % | "
                     f"{'/'.join(map(str, r['cases_jax']))} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/paper_speed"),
                        help="directory for the PNG and JSON (default: out/paper_speed)")
    parser.add_argument("--quick", action="store_true", help="tiny configuration for CI")
    parser.add_argument("--scenes", type=int, default=None, help="faithfulness scenes (default 300; quick 4)")
    parser.add_argument("--pixel-mm", type=float, default=None,
                        help=f"reference pixel size (default {paper_pixel.DEFAULT_PIXEL_MM}; quick 0.4)")
    parser.add_argument("--angle-step", type=float, default=None,
                        help="reference sweep step in rad (default: one pixel of tip travel, pixel / L)")
    parser.add_argument("--ref-sample", type=int, default=None,
                        help="candidates the reference is timed on for the largest batch (default 300)")
    parser.add_argument("--no-rigid", action="store_true", help="skip the rigid-sweep faithfulness")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    quick = args.quick
    links = [2] if quick else [2, 10, 20]
    batches = [1, 4] if quick else [1, 100, 10_000]
    scenes_n = args.scenes if args.scenes is not None else (4 if quick else 300)
    pixel_mm = args.pixel_mm if args.pixel_mm is not None else (0.4 if quick else paper_pixel.DEFAULT_PIXEL_MM)
    ref_sample = args.ref_sample if args.ref_sample is not None else (2 if quick else 300)
    sweeps = ["pcc"] if (quick or args.no_rigid) else ["pcc", "rigid"]
    log = lambda msg: print(msg, file=sys.stderr, flush=True)

    log(f"faithfulness on {scenes_n} scenes ...")
    scenes = faithfulness_scenes(scenes_n)
    faith = faithfulness(scenes, links, sweeps, pixel_mm, args.angle_step, log)
    log("speed ...")
    speed_rows, timed = speed(links, batches, ref_sample, pixel_mm, args.angle_step, 3, log)

    args.out.mkdir(parents=True, exist_ok=True)
    png, raw = args.out / "paper_speed.png", args.out / "paper_speed.json"
    plot(speed_rows, png)
    given = list(argv) if argv is not None else sys.argv[1:]
    command = " ".join(["python benchmarks/bench_paper_speed.py", *given])
    config = {"command": command, "pixel_mm": pixel_mm, "angle_step": args.angle_step,
              "angle_step_text": f"{args.angle_step} rad" if args.angle_step else "pixel / L rad (one pixel of tip travel)",
              "scenes": scenes_n, "links": links, "batches": batches, "ref_sample": ref_sample, "quick": quick,
              "wall_s": time.perf_counter() - start}
    report = {"config": config, "faithfulness": faith, "speed": speed_rows, "timed_agreement": timed}
    raw.write_text(json.dumps(report, indent=1))
    print(tables(config, faith, speed_rows, timed))
    print(f"\nwrote {png} and {raw}")
    return report


if __name__ == "__main__":
    main()

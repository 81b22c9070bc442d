"""The paper's experiments (section V, Tables I and II, Figs. 15-17) against an independent closure.

Run from the repository root:

    .venv/bin/python benchmarks/reproduce_paper.py            # full protocol (about 10 minutes)
    .venv/bin/python benchmarks/reproduce_paper.py --quick    # tiny configuration (CI test)

It writes ``tables.md`` (markdown for benchmarks/RESULTS.md), ``results.json`` (every finger's
errors and cases) and ``contact_sheet_<estimate>.png`` (Fig. 17) to ``--out``
(benchmarks/figures/ by default).

The protocol follows the paper's section V-A on rendered frames:

* the gripper: L = 52 mm (the paper's), r = 4 mm, bases 64 mm apart, Theta 0.55 rad (left) and
  0.45 rad (right); the camera 120 mm away (a D405's intrinsics, colour and depth noise);
* the "observed" closed finger is the elastic-rod model (``synthetic.rod``: 96 segments,
  clamped, uniform stiffness unless ``--stiffness-ratio``/``--base-compliance`` say otherwise, its
  own solver), divided into N equal arc lengths as the paper divides the observed contour;
* calibration per trial: eq. 4 on a rendered frame of the gripper closed on nothing, eq. 5 on a
  rendered open frame (``softgrip_calib.one_frame``);
* estimate from the rendered open frame through the whole vision pipeline (segmentation, keypoints,
  object SDF grid), and the same estimate from the true geometry (true base, Theta, L, r and the
  object's polygon): the difference is what the vision pipeline costs;
* three gripper locations H_a, H_b, H_c (the object's centroid at the open tips' height at H_b; the
  gripper 6 mm lower at H_a, 6 mm higher at H_c), five trials each (noise seeds, up to 0.5 mm of
  gripper jitter and 3 degrees of object rotation);
* Experiment A-a: no object, N = 2, 10, 20. Experiment A-b: the five objects of Table II, N = 20.
  Experiment B: fifteen objects at H_b, the estimate drawn over the observed closed frame.

Errors are eq. 10 at i = N/2 and i = N, mean and standard deviation over both fingers, the three
locations and the trials. The rod's contact case comes from where it touches (within 0.05 mm of
r): a contact run reaching the last half link is the tip, any other run another area.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import sys
import time
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from softgrip_calib.one_frame import frame_measurement, one_frame_from_frames
from softgrip_jax import CASE_NAMES, ContactConfig, FingerFrame, FingerModel, PolygonSDF, estimate_in_frame
from softgrip_vision.keypoints import resample_polyline
from softgrip_vision.overlay import draw_overlay, save_png
_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:  # the test support `synthetic` sits at the root of the checkout
    sys.path.insert(0, _ROOT)
from synthetic.render import Scene, d405_intrinsics, mm_to_px, render  # noqa: E402
from synthetic.rod import RodMechanics, close_rod, observed_joints  # noqa: E402
from synthetic.scenes import gripper_centrelines  # noqa: E402
from synthetic.shapes import ACCURACY_SET, SHAPES, shape  # noqa: E402

LENGTH, HALF_THICKNESS, SEPARATION = 52.0, 4.0, 64.0
THETA = {"left": 0.55, "right": 0.45}
SIDES = ("left", "right")
HANDS = (1.0, -1.0)
CENTRE = np.array([0.0, -40.0])  # gripper centre (between the bases) at H_b, mm
OBJECT_CENTRE = CENTRE + (0.0, LENGTH)  # the object's centroid at the open tips' height at H_b
LOCATIONS = {"H_a": (0.0, 6.0), "H_b": (0.0, 0.0), "H_c": (0.0, -6.0)}  # gripper shift, mm (y down)
OBJECT_SIZE_MM = 30.0
N_VERTICES = 96  # every object resampled to this many vertices: one rod compilation
PLANE_DEPTH_MM = 120.0
INTRINSICS = d405_intrinsics()
FAR_AWAY = PolygonSDF.regular((1.0e4, 1.0e4), 1.0, n_vertices=8)  # "no object" for the true-geometry estimate

#: Paper's Table I (N, i) -> (mean, std) mm and Table II object -> {i: (mean, std)} mm, N = 20.
PAPER_TABLE_I = {(2, 1): (0.77, 0.42), (2, 2): (0.99, 0.40), (10, 5): (0.80, 0.33), (10, 10): (0.96, 0.44),
                 (20, 10): (0.79, 0.30), (20, 20): (0.96, 0.31)}
PAPER_TABLE_II = {"circle": {10: (1.92, 0.25), 20: (1.47, 0.25)}, "square": {10: (2.46, 0.59), 20: (1.09, 0.28)},
                  "clover": {10: (1.72, 0.22), 20: (1.41, 0.37)}, "star_a": {10: (2.03, 0.42), 20: (2.63, 1.38)},
                  "triangle_a": {10: (1.57, 0.44), 20: (0.96, 0.49)}}


@dataclass(frozen=True)
class Variant:
    """One estimate under test: the contact sweep and the deformation method."""

    name: str
    config: ContactConfig
    method: str | None  # None: the core has no ``method`` argument (geometric only)

    def kwargs(self) -> dict:
        return {} if self.method is None else {"method": self.method}


def variants() -> list[Variant]:
    """The paper-faithful estimate, the rigid-sweep reading, and the mechanics one if the core has it."""
    has_method = "method" in inspect.signature(estimate_in_frame).parameters
    geometric = "geometric" if has_method else None
    out = [Variant("paper (PCC sweep)", ContactConfig(), geometric),
           Variant("paper (rigid sweep)", ContactConfig(sweep="rigid"), geometric)]
    if has_method:
        out.append(Variant("mechanics", ContactConfig(), "mechanics"))
    return out


_estimate = eqx.filter_jit(estimate_in_frame)


def estimate_joints(finger: FingerModel, sdf, base: np.ndarray, hand: float, variant: Variant):
    """(joints (N+1, 2) mm, case) of one finger's estimate."""
    frame = FingerFrame(origin=jnp.asarray(base, jnp.float32), angle=jnp.zeros(()), handedness=jnp.asarray(hand))
    est = _estimate(finger, sdf, frame, variant.config, **variant.kwargs())
    return np.asarray(est.joints, np.float64), int(est.case)


def rod_case(in_contact: np.ndarray, n_links: int) -> int:
    """The paper's contact case (0-3) of a rod closure from its nodes' contact flags (M+1,).

    Connected runs of touching nodes are contact areas; one reaching the last half link (arc length
    >= L - L / (2N)) is the tip, any other is another area.
    """
    touching = np.asarray(in_contact, bool)
    m = touching.size - 1
    arc = np.arange(m + 1) / m
    tip_zone = arc >= 1.0 - 0.5 / n_links
    padded = np.concatenate([[False], touching, [False]]).astype(np.int8)
    starts, ends = np.flatnonzero(np.diff(padded) == 1), np.flatnonzero(np.diff(padded) == -1)
    tip = other = False
    for start, end in zip(starts, ends):
        if tip_zone[start:end].any():
            tip = True
        else:
            other = True
    return 0 if not (tip or other) else 1 if not other else 2 if tip else 3


@dataclass(frozen=True)
class Trial:
    """One placement of the gripper (and object): what the frames and the truth say."""

    experiment: str
    object: str | None
    location: str
    trial: int
    centre: np.ndarray  # gripper centre, mm
    polygon: np.ndarray | None  # object outline (V, 2), mm
    closures: tuple  # the rod's closure of each finger


def make_trial(experiment: str, name: str | None, location: str, trial: int, free: dict, rod: RodMechanics,
               jitter: bool = True) -> Trial | None:
    """Place the gripper (and the object) and close the rod; None if a rod closure fails."""
    rng = np.random.default_rng([zlib.crc32(f"{experiment} {name} {location}".encode()), trial])
    shift = rng.uniform(-0.5, 0.5, 2) if jitter else np.zeros(2)
    centre = CENTRE + np.asarray(LOCATIONS[location]) + shift
    bases = centre + np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
    if name is None:
        closures = tuple(replace_base(free[side], base) for side, base in zip(SIDES, bases))
        return Trial(experiment, None, location, trial, centre, None, closures)
    angle = math.radians(rng.uniform(-3.0, 3.0)) if jitter else 0.0
    outline = shape(name, OBJECT_SIZE_MM, angle) + OBJECT_CENTRE
    polygon = resample_polyline(np.vstack([outline, outline[:1]]), N_VERTICES)[:-1]
    sdf = PolygonSDF(jnp.asarray(polygon))
    closures = tuple(close_rod(base, THETA[side], LENGTH, HALF_THICKNESS, sdf, mechanics=rod, handedness=hand)
                     for side, base, hand in zip(SIDES, bases, HANDS))
    if not all(bool(c.converged) for c in closures):
        return None
    return Trial(experiment, name, location, trial, centre, polygon, closures)


@dataclass(frozen=True)
class FreeClosure:
    """A rod closed on nothing, relative to its base (a free closure does not depend on where it is)."""

    points: np.ndarray  # (M+1, 2) mm from the base
    in_contact: np.ndarray


def free_closures(rod: RodMechanics) -> dict:
    out = {}
    for side, hand in zip(SIDES, HANDS):
        closure = close_rod((0.0, 0.0), THETA[side], LENGTH, HALF_THICKNESS, None, mechanics=rod, handedness=hand)
        out[side] = FreeClosure(np.asarray(closure.points), np.asarray(closure.in_contact))
    return out


def replace_base(free: FreeClosure, base: np.ndarray) -> FreeClosure:
    return FreeClosure(free.points + base, free.in_contact)


def observed(closure, n_links: int) -> np.ndarray:
    """(N+1, 2) rod points at N equal arc lengths (the paper's observed positions), mm."""
    if isinstance(closure, FreeClosure):
        points = closure.points
        m = points.shape[0] - 1
        station = np.arange(n_links + 1) * (m / n_links)
        index = np.clip(np.floor(station).astype(int), 0, m - 1)
        frac = (station - index)[:, None]
        return points[index] + frac * (points[index + 1] - points[index])
    return np.asarray(observed_joints(closure, n_links), np.float64)


def frames_of(trial: Trial, seed: int) -> tuple:
    """The rendered open frame (object in place) and closed frame (rod closures) of a trial."""
    opened = Scene(gripper_centrelines(tuple(trial.centre), SEPARATION, LENGTH), half_thickness=HALF_THICKNESS,
                   object_polygon=trial.polygon, plane_depth_mm=PLANE_DEPTH_MM, seed=seed)
    closed = Scene([np.asarray(c.points) for c in trial.closures], half_thickness=HALF_THICKNESS,
                   object_polygon=trial.polygon, plane_depth_mm=PLANE_DEPTH_MM, seed=seed + 1)
    return render(opened, INTRINSICS), render(closed, INTRINSICS)


def calibrate(trial_index: int, free: dict, n_links: int):
    """One-frame calibration (eqs. 4-5) from rendered frames of the gripper closed on nothing and open."""
    centre = CENTRE + np.random.default_rng(9000 + trial_index).uniform(-0.5, 0.5, 2)
    bases = centre + np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
    closed = Scene([f.points + b for f, b in zip((free["left"], free["right"]), bases)],
                   half_thickness=HALF_THICKNESS, plane_depth_mm=PLANE_DEPTH_MM, seed=9100 + 2 * trial_index)
    opened = Scene(gripper_centrelines(tuple(centre), SEPARATION, LENGTH), half_thickness=HALF_THICKNESS,
                   plane_depth_mm=PLANE_DEPTH_MM, seed=9101 + 2 * trial_index)
    return one_frame_from_frames(render(closed, INTRINSICS), render(opened, INTRINSICS), n_links,
                                 label=f"calibration, trial {trial_index}", camera_name="synthetic D405")


def finger_models(profile, n_links: int) -> dict:
    return {side: replace(profile.fingers[side], n_links=n_links).model() for side in SIDES}


def true_models(n_links: int) -> dict:
    return {side: FingerModel(length=LENGTH, theta_entire=THETA[side], half_thickness=HALF_THICKNESS,
                              n_links=n_links) for side in SIDES}


def evaluate(trial: Trial, open_frame, profile, n_values, variant_list) -> tuple[list[dict], dict]:
    """Every finger's eq. 10 errors and cases, from the frames and from the true geometry.

    Returns the records and, per variant, the joints estimated from the frames at the largest N
    (for the contact sheet).
    """
    measured = frame_measurement(open_frame)
    fingers = measured.keypoints
    sdf_frames = measured.object_sdf(open_frame)
    bases_frames = profile.corrected_bases(np.stack([f.base_mm for f in fingers]))
    sdf_truth = FAR_AWAY if trial.polygon is None else PolygonSDF(jnp.asarray(trial.polygon, jnp.float32))
    bases_truth = trial.centre + np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
    records, drawn = [], {}
    for n_links in n_values:
        models = {"frames": finger_models(profile, n_links), "truth": true_models(n_links)}
        for k, (side, hand) in enumerate(zip(SIDES, HANDS)):
            truth = observed(trial.closures[k], n_links)
            case_rod = rod_case(trial.closures[k].in_contact, n_links)
            for variant in variant_list:
                for source, sdf, bases in (("frames", sdf_frames, bases_frames), ("truth", sdf_truth, bases_truth)):
                    joints, case = estimate_joints(models[source][side], sdf, bases[k], hand, variant)
                    error = np.hypot(*(joints - truth).T)
                    records.append(dict(
                        experiment=trial.experiment, object=trial.object, location=trial.location,
                        trial=trial.trial, n_links=n_links, side=side, estimate=variant.name, source=source,
                        error_mid=float(error[n_links // 2]), error_tip=float(error[n_links]),
                        case=CASE_NAMES[case], rod_case=CASE_NAMES[case_rod]))
                    if source == "frames" and n_links == max(n_values):
                        drawn.setdefault(variant.name, []).append(joints)
    return records, drawn


# ---------------------------------------------------------------------------------------------
# Tables


def _select(records, **where):
    return [r for r in records if all(r[k] == v for k, v in where.items())]


def _stat(values) -> str:
    values = np.asarray(values, np.float64)
    return f"{values.mean():.2f} ({values.std():.2f})" if values.size else "-"


def table_i(records, variant_names, n_values) -> str:
    head = "| N | i | paper mean (std) | " + " | ".join(f"{v}: frames | {v}: true geometry" for v in variant_names)
    lines = [head + " |", "|---|---|---|" + "---|---|" * len(variant_names)]
    for n in n_values:
        for key, i in (("error_mid", n // 2), ("error_tip", n)):
            paper = PAPER_TABLE_I.get((n, i))
            cells = [f"{paper[0]:.2f} ({paper[1]:.2f})" if paper else "-"]
            for v in variant_names:
                for source in ("frames", "truth"):
                    cells.append(_stat([r[key] for r in _select(records, experiment="A-a", n_links=n, estimate=v,
                                                                source=source)]))
            lines.append(f"| {n} | {i} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_ii(records, variant_names, objects, n_links) -> str:
    head = "| object | i | paper mean (std) | " + " | ".join(f"{v}: frames | {v}: true geometry" for v in variant_names)
    lines = [head + " |", "|---|---|---|" + "---|---|" * len(variant_names)]
    for name in objects:
        for key, i in (("error_mid", n_links // 2), ("error_tip", n_links)):
            paper = PAPER_TABLE_II.get(name, {}).get(i) if n_links == 20 else None
            cells = [f"{paper[0]:.2f} ({paper[1]:.2f})" if paper else "-"]
            for v in variant_names:
                for source in ("frames", "truth"):
                    cells.append(_stat([r[key] for r in _select(records, experiment="A-b", object=name, estimate=v,
                                                                source=source)]))
            lines.append(f"| {name} | {i} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary(records, variant_names) -> str:
    """Per estimate and experiment: mean errors, the vision pipeline's cost, case agreement."""
    lines = ["| experiment | estimate | fingers | mean error i=N/2, frames / truth (mm) | mean error i=N, frames / truth "
             "(mm) | vision cost i=N/2 / i=N (mm) | case agreement with the rod, frames / truth |",
             "|---|---|---|---|---|---|---|"]
    for experiment in ("A-a", "A-b", "B"):
        for v in variant_names:
            frames = _select(records, experiment=experiment, estimate=v, source="frames")
            truth = _select(records, experiment=experiment, estimate=v, source="truth")
            if not frames:
                continue
            mid_f, mid_t = (np.mean([r["error_mid"] for r in rs]) for rs in (frames, truth))
            tip_f, tip_t = (np.mean([r["error_tip"] for r in rs]) for rs in (frames, truth))
            agree_f, agree_t = (100.0 * np.mean([r["case"] == r["rod_case"] for r in rs]) for rs in (frames, truth))
            lines.append(f"| {experiment} | {v} | {len(frames)} | {mid_f:.2f} / {mid_t:.2f} | {tip_f:.2f} / {tip_t:.2f} "
                         f"| {mid_f - mid_t:+.2f} / {tip_f - tip_t:+.2f} | {agree_f:.0f} % / {agree_t:.0f} % |")
    return "\n".join(lines)


def by_case(records, variant_names) -> str:
    """A-b and B errors at the tip by the rod's contact case: where the paper's cases fall short."""
    contact = [r for r in records if r["experiment"] != "A-a" and r["source"] == "truth"]
    cases = [c for c in CASE_NAMES if _select(contact, rod_case=c)]
    counts = {c: len(_select(contact, rod_case=c, estimate=variant_names[0])) for c in cases}
    lines = ["| estimate (true geometry, A-b and B) | " + " | ".join(f"rod case {c} ({counts[c]} fingers)" for c in cases)
             + " |", "|---|" + "---|" * len(cases)]
    for v in variant_names:
        cells = []
        for c in cases:
            rs = _select(contact, rod_case=c, estimate=v)
            cells.append(f"tip {np.mean([r['error_tip'] for r in rs]):.2f}, mid {np.mean([r['error_mid'] for r in rs]):.2f}"
                         if rs else "-")
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Fig. 17: the estimate drawn over the observed closed frame


def contact_sheet(panels: list[tuple[str, np.ndarray]], path: Path, columns: int = 5) -> Path:
    """Tile labelled RGB panels (all the same size) into one PNG."""
    h, w = panels[0][1].shape[:2]
    rows = -(-len(panels) // columns)
    sheet = np.full((rows * h, columns * w, 3), 255, np.uint8)
    for k, (label, image) in enumerate(panels):
        r, c = divmod(k, columns)
        tile = image.copy()
        cv2.rectangle(tile, (0, 0), (w - 1, 22), (255, 255, 255), -1)
        cv2.putText(tile, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return save_png(path, sheet)


def panel(closed_frame, estimated: list[np.ndarray], trial: Trial, n_links: int) -> np.ndarray:
    """The closed frame cropped around the gripper, estimated joints blue, observed positions green."""
    to_px = lambda p: mm_to_px(p, INTRINSICS, PLANE_DEPTH_MM)
    image = draw_overlay(closed_frame.color, joints=[to_px(j) for j in estimated],
                         observed=[to_px(observed(c, n_links)) for c in trial.closures], radius_px=2, thickness_px=1)
    # A 4:3 window from just above the bases to below the object, so the resize keeps the aspect.
    lo = np.floor(to_px(trial.centre + (-52.0, -8.0))).astype(int)
    hi = np.ceil(to_px(trial.centre + (52.0, 70.0))).astype(int)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, (image.shape[1], image.shape[0]))
    return cv2.resize(image[lo[1]:hi[1], lo[0]:hi[0]], (320, 240), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _machine import describe

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "figures",
                        help="folder for tables.md, results.json and the contact sheets (default: benchmarks/figures)")
    parser.add_argument("--quick", action="store_true", help="tiny configuration: one location, trial and object")
    parser.add_argument("--trials", type=int, default=5, help="trials per location and object (default 5)")
    parser.add_argument("--stiffness-ratio", type=float, default=1.0,
                        help="the rod's base-to-tip stiffness ratio (default 1: uniform)")
    parser.add_argument("--base-compliance", type=float, default=0.0,
                        help="the rod's base compliance (default 0: clamped)")
    args = parser.parse_args(argv)
    if args.trials < 1:
        parser.error("--trials must be >= 1")
    rod = RodMechanics(stiffness_ratio=args.stiffness_ratio, base_compliance=args.base_compliance)
    if args.quick:
        locations, trials, n_a, objects_ab, objects_b = ("H_b",), 1, (2, 4), ("circle",), ("square",)
    else:
        locations, trials, n_a = tuple(LOCATIONS), args.trials, (2, 10, 20)
        objects_ab, objects_b = ACCURACY_SET, tuple(SHAPES)
    n_ab = max(n_a) if args.quick else 20
    command = "    .venv/bin/python benchmarks/reproduce_paper.py " + " ".join(argv if argv is not None else sys.argv[1:])
    t0 = time.perf_counter()
    variant_list = variants()
    names = [v.name for v in variant_list]
    free = free_closures(rod)
    profiles = [calibrate(t, free, n_ab) for t in range(trials)]

    jobs = [("A-a", None, loc, t) for loc in locations for t in range(trials)]
    jobs += [("A-b", name, loc, t) for name in objects_ab for loc in locations for t in range(trials)]
    jobs += [("B", name, "H_b", 0) for name in objects_b]
    records, panels, dropped = [], {v: [] for v in names}, []
    for index, (experiment, name, location, t) in enumerate(tqdm(jobs, desc="scenes", unit="scene", file=sys.stderr)):
        trial = make_trial(experiment, name, location, t, free, rod)
        if trial is None:
            dropped.append(f"{experiment} {name} {location} trial {t}")
            continue
        open_frame, closed_frame = frames_of(trial, seed=2 * index + 17)
        n_values = n_a if experiment == "A-a" else (n_ab,)
        rows, drawn = evaluate(trial, open_frame, profiles[t], n_values, variant_list)
        records += rows
        if experiment == "B":
            for v in names:
                cases = [r["case"] for r in rows if r["estimate"] == v and r["source"] == "frames"]
                rod_cases = [r["rod_case"] for r in rows if r["estimate"] == v and r["source"] == "frames"]
                label = f"{name}: {'/'.join(cases)} (rod {'/'.join(rod_cases)})"
                panels[v].append((label, panel(closed_frame, drawn[v], trial, n_ab)))
    elapsed = time.perf_counter() - t0

    args.out.mkdir(parents=True, exist_ok=True)
    sheets = {}
    for v in names:
        slug = v.split(" (")[0].replace(" ", "_") + ("_rigid" if "rigid" in v else "")
        sheets[v] = contact_sheet(panels[v], args.out / f"contact_sheet_{slug}.png")
    thetas = ", ".join(f"{p.fingers['left'].theta_entire:.4f} / {p.fingers['right'].theta_entire:.4f}" for p in profiles)
    text = "\n\n".join([
        f"Command (from the repository root):\n\n{command.rstrip()}",
        f"Machine: {describe()}. Wall time {elapsed:.0f} s.",
        f"Rod: stiffness ratio {rod.stiffness_ratio}, base compliance {rod.base_compliance}, {rod.n_segments} segments. "
        f"One-frame calibrations (Theta left / right, rad; true 0.55 / 0.45): {thetas}."
        + (f" Dropped (rod not converged): {', '.join(dropped)}." if dropped else ""),
        "### Experiment A-a (no object), eq. 10 mean (std) in mm\n\n" + table_i(records, names, n_a),
        f"### Experiment A-b (objects), N = {n_ab}, eq. 10 mean (std) in mm\n\n" + table_ii(records, names, objects_ab, n_ab),
        "### Summary: errors, vision cost, contact-case agreement\n\n" + summary(records, names),
        "### Error by the rod's contact case (true geometry)\n\n" + by_case(records, names),
        "Contact sheets (Fig. 17): " + ", ".join(f"`{p.name}`" for p in sheets.values()),
    ]) + "\n"
    (args.out / "tables.md").write_text(text)
    (args.out / "results.json").write_text(json.dumps({"records": records, "dropped": dropped,
                                                        "wall_time_s": elapsed}, indent=1))
    print(text)
    return {"records": records, "tables": text, "sheets": sheets}


if __name__ == "__main__":
    main()

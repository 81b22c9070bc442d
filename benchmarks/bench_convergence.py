"""How many fingers the default (mechanics) estimate leaves not converged, over shapes and fingers,
and, against a baseline copy of the package, which of the two lands where the independent rod closes.

Scenes: ten shapes of ``synthetic.shapes`` (30 mm across, turned 0.3 rad, centred at (25, 45) mm),
each sampled on an SDFGrid of 0.4 mm cells by ``PolygonSDF.to_grid`` (the image's SDF stands in for it);
one finger of N = 20 (L 52 mm, r 4 mm) as three mechanics (Theta 0.55 uniform, 0.80 uniform, 0.80
with a base 2.5 times stiffer and base compliance 0.3); ``--bases`` bases uniform in x -14..14 mm,
y -8..14 mm. ``estimate_batch`` at defaults. Prints per finger and shape the fingers with
``mechanics_not_converged``; with ``--base-dir`` (a copy of ``softgrip_jax`` renamed
``softgrip_jax_base``, made as ``compare_estimate.py``'s docstring says) the same for the baseline,
how many fingers differ by more than 1 mm, and for up to ``--rod`` of those the tip's distance to the
closure of the observed-closure rod (``synthetic.rod``, its object exact) for both versions.

    .venv/bin/python benchmarks/bench_convergence.py --base-dir /tmp/sg_base
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SHAPES = ("circle", "square", "triangle_a", "triangle_b", "star_a", "star_b", "clover", "rounded_rect", "heart",
          "cross")
FINGERS = ((0.55, 1.0, 0.0), (0.8, 1.0, 0.0), (0.8, 2.5, 0.3))  # Theta, stiffness ratio, base compliance


def outline(name):
    from synthetic.shapes import shape

    return shape(name, 30.0, 0.3) + np.array([25.0, 45.0])


def sampled(pkg, polygon):
    return pkg.PolygonSDF(vertices=jnp.asarray(polygon, jnp.float32)).to_grid(cell_mm=0.4)


def run(pkg, polygon, finger, bases):
    fm = pkg.FingerModel(length=52.0, theta_entire=finger[0], half_thickness=4.0, n_links=20,
                         stiffness_ratio=finger[1], base_compliance=finger[2])
    sdf = sampled(pkg, polygon)
    est = pkg.estimate_batch(fm, sdf, bases)
    return np.asarray(est.status), np.asarray(est.joints)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bases", type=int, default=3000)
    parser.add_argument("--base-dir", default=None)
    parser.add_argument("--rod", type=int, default=40, help="fingers that differ by > 1 mm checked against the rod")
    args = parser.parse_args()
    import softgrip_jax as new

    versions = {"this tree": new}
    if args.base_dir:
        sys.path.insert(1, args.base_dir)
        import softgrip_jax_base

        versions["baseline"] = softgrip_jax_base
    lost = int(new.Status.MECHANICS_NOT_CONVERGED)
    rng = np.random.default_rng(1)
    bases = np.stack([rng.uniform(-14, 14, args.bases), rng.uniform(-8, 14, args.bases)], 1).astype(np.float32)
    totals = dict.fromkeys(versions, 0)
    differ = []
    for finger in FINGERS:
        for name in SHAPES:
            polygon = outline(name)
            out = {key: run(pkg, polygon, finger, bases) for key, pkg in versions.items()}
            counts = {key: int(np.sum(status == lost)) for key, (status, _) in out.items()}
            for key in versions:
                totals[key] += counts[key]
            line = f"Theta {finger[0]} rho {finger[1]} c {finger[2]} {name:12s} not converged: " + " / ".join(
                f"{counts[key]}" for key in versions)
            if len(out) == 2:
                gap = np.abs(out["this tree"][1] - out["baseline"][1]).max(axis=(1, 2))
                far = np.nonzero(gap > 1.0)[0]
                differ += [(finger, name, i, out["this tree"][1][i, -1], out["baseline"][1][i, -1]) for i in far]
                line += f" | {len(far)} differ > 1 mm"
            print(line, flush=True)
    print("not converged in all (" + " / ".join(versions) + "): " + " / ".join(str(totals[k]) for k in versions)
          + f" of {len(FINGERS) * len(SHAPES) * len(bases)} fingers")
    if differ and args.rod:
        from synthetic.rod import RodMechanics, close_rod, observed_joints

        pick = np.random.default_rng(0).choice(len(differ), min(args.rod, len(differ)), replace=False)
        near = {"this tree": 0, "baseline": 0}
        for j in pick:
            finger, name, i, tip_new, tip_base = differ[j]
            closure = close_rod(bases[i], finger[0], 52.0, 4.0, new.PolygonSDF(vertices=jnp.asarray(outline(name))),
                                mechanics=RodMechanics(stiffness_ratio=finger[1], base_compliance=finger[2]))
            tip = np.asarray(observed_joints(closure, 20))[-1]
            near["this tree"] += int(np.linalg.norm(tip_new - tip) < 1.0)
            near["baseline"] += int(np.linalg.norm(tip_base - tip) < 1.0)
        print(f"of {len(pick)} fingers that differ by > 1 mm, tip within 1 mm of the rod's closure: "
              f"this tree {near['this tree']}, baseline {near['baseline']}")


if __name__ == "__main__":
    main()

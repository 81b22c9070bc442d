"""``softgrip demo``: the estimate on a built-in scene, printed (needs no camera and no files)."""

from __future__ import annotations

import argparse
import json
import sys
import time

EPILOG = """examples:
  softgrip demo            # both fingers of a 52 mm gripper closing on a 30 mm circle, as a table
  softgrip demo --json     # the same as one JSON object on stdout
"""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="run the estimator on a built-in scene", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Estimate where each finger of a built-in gripper touches a built-in object "
                    "and what shape it takes (the paper's pipeline on exact geometry).",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    from softgrip_jax import CASE_NAMES, FingerModel, Gripper, PolygonSDF, estimate_grasp

    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    scenes = {
        "circle between the fingers": (PolygonSDF.regular((0.0, 38.0), 15.0, 256), (0.0, 0.0, 0.0)),
        "circle off-centre": (PolygonSDF.regular((0.0, 38.0), 15.0, 256), (12.0, 0.0, 0.0)),
        "no object in reach": (PolygonSDF.regular((0.0, 150.0), 15.0, 256), (0.0, 0.0, 0.0)),
    }
    t0 = time.perf_counter()
    results = []
    estimate = eqx.filter_jit(estimate_grasp)  # one compilation for all three scenes
    for name, (sdf, pose) in scenes.items():
        est = estimate(gripper, sdf, jnp.asarray(pose, jnp.float32))
        for side, e in (("left", est.left), ("right", est.right)):
            results.append({
                "scene": name, "side": side, "case": CASE_NAMES[int(e.case)], "valid": bool(e.valid),
                "n_g1": round(float(e.contact.n_g1), 3) if int(e.case) else None,
                "contact_mm": np.round(np.asarray(e.contact.p_o1), 2).tolist() if int(e.case) else None,
                "tip_mm": np.round(np.asarray(e.joints[-1]), 2).tolist(),
                "joints_mm": np.round(np.asarray(e.joints), 2).tolist(),
            })
    elapsed = time.perf_counter() - t0
    if args.json:
        json.dump({"finger": {"length": 52.0, "theta_entire": 0.55, "half_thickness": 4.0, "n_links": 10},
                   "base_separation": 56.0, "results": results}, sys.stdout)
        print()
        return 0
    print("gripper: two 52 mm fingers, Theta = 0.55 rad, N = 10, bases 56 mm apart; object: 30 mm circle")
    print(f"{'scene':<28} {'finger':<6} {'case':<14} {'N_g1':>6}  {'contact (mm)':<16} {'tip (mm)':<16}")
    for r in results:
        contact = "-" if r["contact_mm"] is None else "({:.1f}, {:.1f})".format(*r["contact_mm"])
        n_g1 = "-" if r["n_g1"] is None else f"{r['n_g1']:.2f}"
        print(f"{r['scene']:<28} {r['side']:<6} {r['case']:<14} {n_g1:>6}  {contact:<16} "
              "({:.1f}, {:.1f})".format(*r["tip_mm"]))
    print(f"({elapsed:.1f} s including compilation)", file=sys.stderr)
    return 0

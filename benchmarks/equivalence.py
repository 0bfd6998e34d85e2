"""Behaviour fingerprint of the calibration: bit for bit, before and after a restructuring.

Run: ``python benchmarks/equivalence.py --write benchmarks/results/equivalence.json`` on the code
before a change, then ``python benchmarks/equivalence.py --check benchmarks/results/equivalence.json``
after it (exit 1 and the differing fields where anything differs).

Nine calibrations of simulated scenes that exercise the whole schedule (not only the preset):

1. the paper preset, 10 lasers, 16 views, 0.5 px, free board poses;
2. the same, the rigid box (pass R);
3. 3 lasers, 5 views, 0.3 px;
4. 6 lasers, 8 views, 0.3 px, 10 % of the spots given the next laser's label and four dots
   moved 20 px (relabelling, outliers, repairs);
5. 8 lasers, 12 sensor poses drawn from their own seed, 0.5 px, rigid;
6. 5 lasers, 9 views, 0.3 px, the true camera given and frozen (``freeze={"camera"}``);
7. 4 lasers, 7 views, 0.9 px;
8-9. two 3-laser 6-view scenes calibrated together by ``calibrate_many(batch="vmap")``.

For each: the SHA-256 of every parameter and covariance array (their bytes), the passes (name,
steps, outcome, limit, notes, costs, scale), the repairs, the per-kind noise, and the SHA-256 of
the report and of the calibration file (``to_calibration``; its timings and the problem it
carries left out), with a few
readable figures beside them.  The Cramer-Rao bound of scene 1 is fingerprinted too.
"""

import argparse
import copy
import hashlib
import json
import sys
from pathlib import Path

import numpy as np


def _sha(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:24]


def _json_sha(doc) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=repr).encode()).hexdigest()[:24]


def _scene(n_lasers: int, n_views: int, seed: int | None = None):
    from slcvjax import box_scene, make_scene, paper_rig
    from slcvjax.observations.simulate import PAPER_ROTATION_DEG, PAPER_TRANSLATION_MM

    if seed is None:
        return make_scene("paper", n_lasers=n_lasers, n_views=n_views)
    rng = np.random.default_rng(seed)
    views = np.zeros((n_views, 6))
    views[1:, :3] = np.radians(rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_ROTATION_DEG))
    views[1:, 3:] = rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_TRANSLATION_MM)
    return box_scene(paper_rig(n_lasers), views)


def _corrupt(obs, seed: int):
    """10 % of the spots given the next laser's label and four dots moved 20 px."""
    obs = copy.deepcopy(obs)
    rng = np.random.default_rng(seed)
    spots = [(v, j) for v, view in enumerate(obs.views) for j in range(len(view.spots))]
    for i in rng.choice(len(spots), max(2, round(0.1 * len(spots))), replace=False):
        v, j = spots[i]
        obs.views[v].spots[j].laser = (obs.views[v].spots[j].laser + 1) % obs.n_lasers
    dots = [
        (v, b, j) for v, view in enumerate(obs.views) for b, (_, s) in view.boards.items() for j in np.flatnonzero(s)
    ]
    for i in rng.choice(len(dots), 4, replace=False):
        v, b, j = dots[i]
        obs.views[v].boards[b][0][j] += 20.0 * np.array([0.6, -0.8])
    return obs


def fingerprint(res, obs) -> dict:
    """The fingerprint of one calibration result (see the module docstring)."""
    import jax

    from slcvjax import report, to_calibration
    from slcvjax.observations.formats import calibration_to_json

    rep = report(res, obs)
    cal = calibration_to_json(to_calibration(res, obs))
    cal["stages"]["joint"].pop("timings_s", None)
    cal.pop("problem", None)  # the problem the file carries (its content: the fingerprints above)
    return {
        "params": _sha(*jax.tree_util.tree_leaves(res.params)),
        "cov": _sha(res.cov.glob, res.cov.blocks, res.cov.sigma, res.cov.dof),
        "passes": [
            [p.name, p.steps, p.code.label, p.limit, list(p.notes), repr(p.cost0), repr(p.cost), repr(p.scale)]
            for p in res.passes
        ],
        "repairs": json.loads(json.dumps([r.to_json() for r in res.repairs], default=repr)),
        "kind_sigma": {k: repr(v) for k, v in res.kind_sigma.items()},
        "undetermined": list(res.undetermined_lasers),
        "report": _json_sha(rep),
        "calibration_file": _json_sha(cal),
        "rms_px": rep["residuals"]["rms_px"],
        "loss": [res.loss, repr(res.scale)],
    }


def run() -> dict:
    import slcvjax as sj

    out = {}

    def one(name, obs, **kw):
        print(f"{name} ...", file=sys.stderr, flush=True)
        out[name] = fingerprint(sj.calibrate(obs, **kw), obs)

    obs1, truth1 = sj.simulate(_scene(10, 16), noise=0.5, seed=1)
    one("1_preset_free", obs1)
    one("2_preset_rigid", obs1, rigid=True)
    one("3_three_lasers", sj.simulate(_scene(3, 5), noise=0.3, seed=2)[0])
    one("4_wrong_labels", _corrupt(sj.simulate(_scene(6, 8), noise=0.3, seed=3)[0], seed=4))
    one("5_eight_lasers_rigid", sj.simulate(_scene(8, 12, seed=7), noise=0.5, seed=5)[0], rigid=True)
    obs6, truth6 = sj.simulate(_scene(5, 9, seed=8), noise=0.3, seed=6)
    one("6_frozen_camera", obs6, camera=truth6.rig.camera, freeze={"camera"})
    one("7_noisy", sj.simulate(_scene(4, 7, seed=9), noise=0.9, seed=7)[0])
    pair = [sj.simulate(_scene(3, 6, seed=s), noise=0.3, seed=s)[0] for s in (11, 12)]
    print("8-9 vmap ...", file=sys.stderr, flush=True)
    for k, (res, o) in enumerate(zip(sj.calibrate_many(pair, batch="vmap"), pair, strict=True)):
        out[f"{8 + k}_vmap"] = fingerprint(res, o)
    bound = sj.cramer_rao(truth1, obs1, 0.5)
    out["bound_preset"] = {
        "cov": _sha(bound["cov"].glob, bound["cov"].blocks),
        "position_std_mm": _sha(bound["position_std_mm"]),
        "direction_std_rad": _sha(bound["direction_std_rad"]),
    }
    return out


def _diff(a, b, where="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only in {'the reference' if k in a else 'this run'}")
            else:
                out += _diff(a[k], b[k], f"{where}.{k}")
        return out
    return [] if a == b else [f"{where}: reference {a!r}, now {b!r}"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", type=Path, help="write the fingerprints to this file")
    g.add_argument("--check", type=Path, help="compare with the fingerprints in this file")
    args = ap.parse_args(argv)
    now = run()
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.write} ({len(now)} entries)")
        return 0
    diffs = _diff(json.loads(args.check.read_text()), json.loads(json.dumps(now)))
    for d in diffs:
        print(d)
    print(f"{len(now)} entries: " + ("identical" if not diffs else f"{len(diffs)} difference(s)"))
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())

"""Speed of ``cosy match`` and ``cosy refine`` as a user runs them: whole processes, start-up
included, on the reference workload of 100 groups of 4 views x 6 objects (table scenes of
``tests/multiview_fixtures.make_table_dataset``, seed 2; realistic candidates without misses or
false positives, seed 0; no images, so refine has no image check), milliseconds per group.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_multiview_speed.py [--repeats 7]
        [--src NAME=PATH ...] [--work DIR]

``--src NAME=PATH`` runs the same commands with another checkout's ``src`` first on the
``PYTHONPATH`` (a ``git worktree`` of the commit before a change), interleaved with this one, so
that the machine's load is the same for both: the figures to compare are side by side in one run.
The minimum over the repeats is the figure (the machine is shared; medians are printed too).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
COSY = [str(Path(sys.executable).parent / "cosy")]
N_GROUPS = 100


def timed(cmd: list[str], src: str | None) -> float:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if src:
        env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr}")
    return dt


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--src", action="append", default=[], help="NAME=PATH of another checkout's src folder")
    ap.add_argument("--work", type=Path)
    args = ap.parse_args(argv)
    from multiview_fixtures import make_table_dataset

    from cosy_cli.synth import candidates as synth_candidates

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_mv_speed_"))
    work.mkdir(parents=True, exist_ok=True)
    data = work / "many"
    cands = work / "many.csv"
    if not cands.exists():
        make_table_dataset(data, n_scenes=N_GROUPS, n_views=4, n_objects=6, seed=2, models="synth")
        synth_candidates.main(data, "test", cands, profile="realistic", seed=0, log=lambda *_: None,
                              p_miss=0.0, fp_per_image=0.0)
    impls = [("this checkout", None)] + [tuple(s.split("=", 1)) for s in args.src]
    t = {n: {"match": [], "refine": []} for n, _ in impls}
    for k in range(args.repeats):
        for name, src in impls:
            tag = name.replace(" ", "_")
            md, rd = work / f"match_{tag}", work / f"refine_{tag}"
            t[name]["match"].append(timed(COSY + ["match", "--dataset", str(data), "--candidates", str(cands),
                                                  "--out", str(md), "--overwrite"], src))
            t[name]["refine"].append(timed(COSY + ["refine", "--dataset", str(data), "--matches", str(md),
                                                   "--out", str(rd), "--overwrite"], src))
    print(f"# {N_GROUPS} groups of 4 views x 6 objects, whole processes with start-up, {args.repeats} repeats "
          f"interleaved; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; ms per group, min (median)")
    for name, _ in impls:
        m, r = np.array(t[name]["match"]), np.array(t[name]["refine"])
        print(f"{name:>16}: match {m.min() / N_GROUPS * 1e3:6.2f} ({np.median(m) / N_GROUPS * 1e3:6.2f})   "
              f"refine {r.min() / N_GROUPS * 1e3:6.2f} ({np.median(r) / N_GROUPS * 1e3:6.2f})   "
              f"both {(m + r).min() / N_GROUPS * 1e3:6.2f}")


if __name__ == "__main__":
    main()

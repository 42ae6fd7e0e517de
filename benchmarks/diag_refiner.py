"""Does a refiner run learn anything? Compare its disentangled loss with the loss of the identity
update ("do nothing") on fresh training samples at several perturbation sizes.

    python benchmarks/diag_refiner.py --run runs/refiner [--crop 64x48] [--dataset data_samples]
"""
import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from cosy_cli.singleview.networks.losses import disentangled_loss, pad_symmetries  # noqa: E402
from cosy_cli.singleview.networks.model import prepare_inputs  # noqa: E402
from cosy_cli.singleview.networks.pose_update import identity_output  # noqa: E402
from cosy_cli.training.data import SampleGenerator  # noqa: E402
from cosy_cli.training.train import _load_objects, load_run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None, help="a cosy train run folder (refiner or coarse)")
    ap.add_argument("--dataset", default="data_samples")
    ap.add_argument("--batches", type=int, default=4)
    args = ap.parse_args()
    if args.run is None or not (Path(args.run) / "checkpoint.pt").is_file():
        print("diag_refiner: no training run given (--run RUN_DIR with a checkpoint.pt); nothing to measure")
        return
    torch.set_num_threads(1)
    model, ck = load_run(args.run)
    import json
    cfg = json.loads((Path(args.run) / "config.json").read_text())
    db, K, size = _load_objects(Path(args.dataset), 300, 0)
    points = torch.as_tensor(np.stack([o.points for o in db]), dtype=torch.float32)
    syms = pad_symmetries([o.symmetries for o in db])
    gen = SampleGenerator(db, seed=123, kind=cfg["kind"], crop_size=tuple(cfg["crop_size"]), K=K, image_size=size)
    f = (lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32))
    print(f"run {args.run} at step {ck['step']}: mean loss (mm) on fresh samples, network vs identity update")
    print(f"{'curriculum':>10} {'who':>9} {'xy':>7} {'z':>7} {'rot':>7} {'total':>7}")
    for c in (0.3, 0.6, 1.0):
        gen.curriculum = c
        acc = {"network": [], "identity": []}
        for _ in range(args.batches):
            b = gen.batch(32)
            x = torch.from_numpy(prepare_inputs(b["observed"], b["rendered"],
                                                b["rendered_mask"] if cfg.get("n_inputs") == 7 else None))
            oi = torch.as_tensor(b["obj_index"], dtype=torch.long)
            args_ = (f(b["T_input"]), f(b["T_gt"]), f(b["K_crop"]), points[oi], syms[oi])
            with torch.no_grad():
                for who, out in (("network", model(x)), ("identity", identity_output(len(oi)))):
                    acc[who].append({k: float(v.mean()) for k, v in disentangled_loss(out, *args_).items()})
        for who, rows in acc.items():
            m = {k: np.mean([r[k] for r in rows]) for k in rows[0]}
            print(f"{c:>10.1f} {who:>9} {m['xy']:>7.2f} {m['z']:>7.2f} {m['rot']:>7.2f} {m['total']:>7.2f}")


if __name__ == "__main__":
    main()

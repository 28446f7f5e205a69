"""The first front-camera frame (after the crop, as the policy sees it) of every built-in task, written to
docs/images/<task>_front.png, to compare the framing with the reference study's crops.

    python benchmarks/task_frames.py                       # preset reference, grid state 0
    python benchmarks/task_frames.py --preset fast --tasks push-t
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=["push-t", "rope-routing", "toy-packing"])
    p.add_argument("--preset", default="reference")
    p.add_argument("--init-state", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "images")
    args = p.parse_args()
    from PIL import Image

    from twinbench._runtime import quiet_warp
    from twinbench.tasks import get_task

    quiet_warp()
    args.out.mkdir(parents=True, exist_ok=True)
    for task in args.tasks:
        env = get_task(task).make_env(preset=args.preset)
        obs, _ = env.reset(seed=0, options={"init_state": args.init_state})
        path = args.out / f"{task}_front.png"
        Image.fromarray(obs["pixels"]["front"]).save(path)
        print(f"{task}: {path} {obs['pixels']['front'].shape}", flush=True)
        env.close()


if __name__ == "__main__":
    main()

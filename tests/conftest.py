"""Shared test fixtures: the golden-data folder (in the repository) and device selection."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parent / "data"


class Processes:
    """Linux /proc views of the processes a test started (tests of killed and interrupted runs)."""

    @staticmethod
    def children(pid: int) -> list[int]:
        try:
            return [int(c) for t in Path(f"/proc/{pid}/task").iterdir()
                    for c in (t / "children").read_text().split()]
        except OSError:
            return []

    @classmethod
    def descendants(cls, pid: int) -> list[int]:
        kids = cls.children(pid)
        return kids + [g for k in kids for g in cls.descendants(k)]

    @staticmethod
    def cmdline(pid: int) -> str:
        try:
            return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            return ""

    @staticmethod
    def alive(pid: int) -> bool:
        """Running (a zombie waiting for a reaper counts as ended)."""
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
        except OSError:
            return False

    @classmethod
    def wait_ended(cls, pids, seconds: float) -> list[int]:
        """Wait up to `seconds` for `pids` to end; returns those still running."""
        import time

        deadline = time.monotonic() + seconds
        while any(cls.alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.05)
        return [p for p in pids if cls.alive(p)]


@pytest.fixture
def processes() -> type[Processes]:
    return Processes


@pytest.fixture(scope="session")
def phystwin_reference() -> Path:
    """Folder with PhysTwin's golden trajectories: the repository's copy (tests/data/phystwin, every frame
    and a subset of substeps), or the full files where $TWINBENCH_GOLDEN_DIR points to them."""
    folder = Path(os.environ.get("TWINBENCH_GOLDEN_DIR") or DATA / "phystwin")
    if not (folder / "drop.npz").is_file():
        raise FileNotFoundError(f"golden data not found at {folder}: TWINBENCH_GOLDEN_DIR must name a folder "
                                "with PhysTwin's golden NPZ files (drop.npz, ...)")
    return folder


@pytest.fixture(scope="session")
def sysid_small():
    """A 6-frame synthetic rope for system identification's input and format tests (last 2 held out)."""
    from twinbench.construct.sysid_synthetic import synthetic_case

    return synthetic_case("rope", frames=6, validation_frames=2, seed=5)[0]


def _cuda_available() -> bool:
    import warp as wp

    wp.init()
    return wp.get_cuda_device_count() > 0


def pytest_collection_modifyitems(config, items):
    if any("gpu" in item.keywords for item in items) and not _cuda_available():
        skip = pytest.mark.skip(reason="needs a CUDA device; none is present on this machine")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def fast_env():
    """A push-T env on the built-in `fast` cell with early termination on success (quick expert
    episodes), built once per session (each test resets it)."""
    from twinbench.env import TwinEnv

    env = TwinEnv("push-t", preset="fast", success_rule="early")
    env.reset(seed=0, options={"init_state": 0})
    return env


@pytest.fixture(scope="session")
def tiny_act_checkpoint(tmp_path_factory):
    """A random, small LeRobot ACT policy for the push-T env's spaces (front + wrist 240x240, state and
    action [x, y]), saved with its processors (normalisation stats given) as lerobot-train would.
    Skips without the lerobot extra; nothing is downloaded (random backbone)."""
    pytest.importorskip("lerobot", reason="needs the lerobot extra (make install EXTRAS='dev lerobot')")
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    out = tmp_path_factory.mktemp("act") / "pretrained_model"
    cams = ("front", "wrist")
    inputs = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 240, 240)) for c in cams}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (2,))
    torch.manual_seed(0)
    action = {"action": PolicyFeature(FeatureType.ACTION, (2,))}
    cfg = ACTConfig(input_features=inputs, output_features=action,
                    chunk_size=4, n_action_steps=2, dim_model=32, n_heads=2, dim_feedforward=64,
                    n_encoder_layers=1, n_decoder_layers=1, use_vae=False, pretrained_backbone_weights=None,
                    device="cpu")
    policy = ACTPolicy(cfg)
    stats = {"observation.state": {"mean": torch.tensor([0.5, 0.0]), "std": torch.tensor([0.1, 0.1])},
             "action": {"mean": torch.tensor([0.5, 0.0]), "std": torch.tensor([0.05, 0.05])}}
    for c in cams:
        stats[f"observation.images.{c}"] = {"mean": torch.full((3, 1, 1), 0.5),
                                            "std": torch.full((3, 1, 1), 0.25)}
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out


@pytest.fixture(autouse=True)
def _task_registry_restored():
    """Tasks a test registers (test doubles) are forgotten after it, so no test sees another's tasks."""
    from twinbench import tasks

    tasks.task_names()  # the package's own tasks, discovered once before the snapshot
    saved = dict(tasks._TASKS)
    yield
    tasks._TASKS.clear()
    tasks._TASKS.update(saved)

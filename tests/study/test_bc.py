"""The study's behaviour cloning: checkpoints per data size and epoch count, each with its training loss,
loadable as `cnn:` policy specs; a second call reuses them. (Recording needs a real workcell: the study's
end-to-end run covers it.)"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")

from twinbench.errors import InputError  # noqa: E402
from twinbench.policies import parse_policy_spec  # noqa: E402
from twinbench.policies.cnn import load_policy  # noqa: E402
from twinbench.study.bc import bc_size, train_checkpoints  # noqa: E402


def demos(n_episodes: int = 3, steps: int = 6, size: int = 16) -> dict:
    rng = np.random.default_rng(0)
    n = n_episodes * steps
    return {"images": rng.integers(0, 255, (n, size, size, 3), dtype=np.uint8),
            "agent_pos": rng.uniform(0.2, 0.6, (n, 2)).astype(np.float32),
            "actions": rng.uniform(0.2, 0.6, (n, 2)).astype(np.float32),
            "episode": np.repeat(np.arange(n_episodes), steps).astype(np.int32)}


def test_checkpoints_per_data_size_and_epochs(tmp_path):
    data = demos()
    logs = []
    paths = train_checkpoints(data, tmp_path, (1, 3, 9), (1, 2), image_size=16, log=logs.append)
    # data size 9 is capped at the 3 demonstrations there are (the same checkpoints as size 3)
    assert [p.name for p in paths] == ["bc-d1-e1", "bc-d1-e2", "bc-d3-e1", "bc-d3-e2"]
    for p in paths:
        rec = json.loads((p / "train.json").read_text())
        assert rec["frames"] == 6 * rec["demos"] and len(rec["loss_per_epoch"]) == rec["epochs"]
        assert rec["loss"] == rec["loss_per_epoch"][-1] > 0
        cfg, _ = load_policy(p)
        assert cfg.extra["demos"] == rec["demos"] and cfg.relative
        spec = parse_policy_spec(f"{p.name}=cnn:{p}")
        assert (spec.kind, spec.name, spec.checkpoint) == ("cnn", p.name, p.name)
    # the 1-epoch checkpoint is the 2-epoch run after its first epoch
    one, two = (json.loads((tmp_path / f"bc-d3-e{e}" / "train.json").read_text()) for e in (1, 2))
    assert two["loss_per_epoch"][0] == one["loss"]
    # again: nothing is retrained
    logs.clear()
    assert train_checkpoints(data, tmp_path, (1, 3, 9), (1, 2), image_size=16, log=logs.append) == paths
    assert logs == []


def test_unknown_size():
    with pytest.raises(InputError, match="small"):
        bc_size("huge")

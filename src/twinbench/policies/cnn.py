"""A small CNN policy with action chunks, trained by behaviour cloning on CPU (policy kind `cnn`, spec
`[NAME=]cnn:DIR[?n_action_steps=N]`; needs the `torch` extra).

Input: one camera's image (default "front") downsampled to `image_size` squared, with two pixel-coordinate
channels, and the normalised `agent_pos`; output: a chunk of `chunk` future actions, relative to
`agent_pos` when the action and agent_pos have the same size (push-T's planar targets), normalised per
dimension. The policy executes the first `n_action_steps` actions of each chunk open loop
(`ChunkedPolicy`), clipped to the env's action bounds.

A checkpoint is a directory: config.json (`CNNConfig`, with the normalisation statistics) and
weights.pt, a plain state_dict of tensors (`torch.save`), read with `torch.load(weights_only=True)`: no
object is unpickled. Training (`train`) is seeded and deterministic on CPU for a given thread count.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from twinbench.errors import InputError, PolicyError
from twinbench.policies.base import ChunkedPolicy

FORMAT = "twinbench-cnn-policy"
WEIGHTS = "weights.pt"


def _torch():
    try:
        import torch
    except ImportError:
        raise InputError("the cnn policy needs torch: install the `torch` extra "
                         "(pip install 'twinbench[torch]', or make install EXTRAS=\"dev torch\")") from None
    return torch


@dataclass(frozen=True)
class CNNConfig:
    """A CNN policy's architecture, inputs and normalisation (config.json)."""

    state_dim: int
    action_dim: int
    camera: str = "front"
    image_size: int = 64
    chunk: int = 8
    n_action_steps: int = 4
    channels: tuple[int, ...] = (32, 64, 64, 64)
    hidden: int = 256
    relative: bool = True  # actions predicted relative to agent_pos (needs state_dim == action_dim)
    state_mean: tuple[float, ...] = ()
    state_std: tuple[float, ...] = ()
    action_mean: tuple[float, ...] = ()  # of the (relative) targets, per action dimension
    action_std: tuple[float, ...] = ()
    extra: dict = field(default_factory=dict)  # free labels (training record)

    def to_dict(self) -> dict:
        return {"format": FORMAT, "version": 1, **asdict(self)}

    @classmethod
    def from_dict(cls, d: dict, where: str = "cnn config") -> CNNConfig:
        d = dict(d)
        if d.pop("format", None) != FORMAT or d.pop("version", None) != 1:
            raise InputError(f"{where}: not a cnn policy config (expected format {FORMAT!r}, version 1); "
                             "write it with twinbench.policies.cnn.save_policy")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown or "state_dim" not in d or "action_dim" not in d:
            raise InputError(f"{where}: fields must be among {sorted(known)} with state_dim and action_dim "
                             f"required; unknown: {unknown}")
        for k in ("channels", "state_mean", "state_std", "action_mean", "action_std"):
            if k in d:
                d[k] = tuple(d[k])
        cfg = cls(**d)
        if cfg.relative and cfg.state_dim != cfg.action_dim:
            raise InputError(f"{where}: relative actions need state_dim == action_dim, got "
                             f"{cfg.state_dim} and {cfg.action_dim}")
        if not (cfg.image_size >= 16 and cfg.chunk >= 1 and 1 <= cfg.n_action_steps <= cfg.chunk):
            raise InputError(f"{where}: need image_size >= 16, chunk >= 1, 1 <= n_action_steps <= chunk")
        return cfg


def build_net(cfg: CNNConfig):
    """The network: strided 3x3 convolutions (the first 5x5) over RGB + 2 coordinate channels, flattened,
    concatenated with the normalised state, then an MLP to chunk x action_dim."""
    torch = _torch()
    nn = torch.nn

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            layers, c_in, size = [], 5, cfg.image_size
            for i, c in enumerate(cfg.channels):
                k = 5 if i == 0 else 3
                layers += [nn.Conv2d(c_in, c, k, stride=2, padding=k // 2), nn.ReLU()]
                c_in, size = c, (size + 1) // 2
            self.conv = nn.Sequential(*layers)
            self.mlp = nn.Sequential(nn.Linear(c_in * size * size + cfg.state_dim, cfg.hidden), nn.ReLU(),
                                     nn.Linear(cfg.hidden, cfg.hidden), nn.ReLU(),
                                     nn.Linear(cfg.hidden, cfg.chunk * cfg.action_dim))
            s = torch.linspace(-1.0, 1.0, cfg.image_size)
            self.register_buffer("coords", torch.stack(torch.meshgrid(s, s, indexing="ij"))[None],
                                 persistent=False)

        def forward(self, images, state):
            """images (B, 3, S, S) float in [0, 1], state (B, state_dim) normalised -> (B, chunk, A)."""
            x = torch.cat([images - 0.5, self.coords.expand(len(images), -1, -1, -1)], 1)
            x = self.conv(x).flatten(1)
            return self.mlp(torch.cat([x, state], 1)).view(-1, cfg.chunk, cfg.action_dim)

    return Net()


# ---- data -------------------------------------------------------------------------------------------------
def episode_window(episode: np.ndarray, offsets) -> tuple[np.ndarray, np.ndarray]:
    """(idx, pad), each (N, len(offsets)): per step, the indices of the steps at `offsets` from it, clamped
    to its own episode (`episode`: the episode index per step, episodes contiguous), and where clamping
    replaced a step that lies outside the episode."""
    episode = np.asarray(episode)
    n = len(episode)
    ends = np.r_[np.nonzero(np.diff(episode))[0], n - 1]
    starts = np.r_[0, ends[:-1] + 1]
    first, last = np.repeat(starts, ends - starts + 1), np.repeat(ends, ends - starts + 1)
    raw = np.arange(n)[:, None] + np.asarray(offsets, np.int64)[None]
    idx = np.clip(raw, first[:, None], last[:, None])
    return idx, idx != raw


def chunk_targets(actions: np.ndarray, episode: np.ndarray, chunk: int) -> np.ndarray:
    """(N, chunk, A): for each step, its action and the next chunk - 1 of its episode (the episode's last
    action repeated past its end)."""
    return np.asarray(actions, np.float32)[episode_window(episode, np.arange(chunk))[0]]


def image_tensor(images: np.ndarray, torch):
    """(N, H, W, 3) uint8 -> (N, 3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.array(images, np.uint8)).permute(0, 3, 1, 2).float() / 255.0


def random_shift(images, pad: int, gen, torch):
    """Random shifts by up to `pad` pixels (replicate padding), one per image, from generator `gen`."""
    if pad == 0:
        return images
    n, _, h, w = images.shape
    padded = torch.nn.functional.pad(images, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (n,), generator=gen)
    dy = torch.randint(0, 2 * pad + 1, (n,), generator=gen)
    rows = (dy[:, None] + torch.arange(h)[None])[:, None, :, None].expand(n, 3, h, w + 2 * pad)
    out = torch.gather(padded, 2, rows)
    cols = (dx[:, None] + torch.arange(w)[None])[:, None, None, :].expand(n, 3, h, w)
    return torch.gather(out, 3, cols)


class Adam:
    """Adam (Kingma & Ba) over a module's parameters. `torch.optim` imports torch._dynamo when an
    optimiser is made (about 10 s of CPU per process), more than a whole small training run."""

    def __init__(self, params, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params = [p for p in params if p.requires_grad]
        self.lr, self.betas, self.eps, self.t = lr, betas, eps, 0
        self.m = [p.detach().new_zeros(p.shape) for p in self.params]
        self.v = [p.detach().new_zeros(p.shape) for p in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        b1, b2 = self.betas
        self.t += 1
        c1, c2 = 1 - b1**self.t, 1 - b2**self.t
        for p, m, v in zip(self.params, self.m, self.v, strict=True):
            if p.grad is None:
                continue
            g = p.grad.detach()
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            p.data.addcdiv_(m, (v / c2).sqrt_().add_(self.eps), value=-self.lr / c1)


def make_config(agent_pos: np.ndarray, actions: np.ndarray, episode: np.ndarray, **settings) -> CNNConfig:
    """A config whose normalisation statistics come from the demonstrations."""
    agent_pos, actions = np.asarray(agent_pos, np.float64), np.asarray(actions, np.float64)
    base = CNNConfig(state_dim=agent_pos.shape[1], action_dim=actions.shape[1], **settings)
    relative = base.relative and base.state_dim == base.action_dim
    target = chunk_targets(actions, episode, base.chunk).astype(np.float64)
    if relative:
        target = target - agent_pos[:, None]
    flat = target.reshape(-1, base.action_dim)
    return CNNConfig(**{**asdict(base), "relative": relative,
                        "state_mean": tuple(agent_pos.mean(0).tolist()),
                        "state_std": tuple(np.maximum(agent_pos.std(0), 1e-6).tolist()),
                        "action_mean": tuple(flat.mean(0).tolist()),
                        "action_std": tuple(np.maximum(flat.std(0), 1e-6).tolist())})


def train(cfg: CNNConfig, images: np.ndarray, agent_pos: np.ndarray, actions: np.ndarray,
          episode: np.ndarray, *, epochs: int, seed: int = 0, batch_size: int = 64, lr: float = 1e-3,
          shift_px: int = 4, threads: int = 1, snapshots=(), on_snapshot=None, log=None):
    """Train a CNN policy by behaviour cloning (MSE on normalised action chunks, Adam, random-shift
    augmentation). Returns (net, per-epoch mean training losses). Seeded: the same inputs, seed and
    `threads` give the same weights. `on_snapshot(epoch, net, losses)` is called after each epoch listed
    in `snapshots`."""
    torch = _torch()
    n = len(images)
    if not (len(agent_pos) == len(actions) == len(episode) == n) or n == 0:
        raise InputError(f"cnn training data: images, agent_pos, actions and episode must have the same "
                         f"non-zero length, got {[len(images), len(agent_pos), len(actions), len(episode)]}")
    old_threads = torch.get_num_threads()
    torch.set_num_threads(int(threads))
    try:
        torch.manual_seed(seed)
        net = build_net(cfg)
        opt = Adam(net.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(seed)
        rng = np.random.default_rng(seed)
        x_img = image_tensor(images, torch)
        state = (np.asarray(agent_pos) - np.asarray(cfg.state_mean)) / cfg.state_std
        x_state = torch.from_numpy(state.astype(np.float32))
        target = chunk_targets(actions, episode, cfg.chunk)
        if cfg.relative:
            target = target - np.asarray(agent_pos, np.float32)[:, None]
        y = torch.from_numpy(((target - np.asarray(cfg.action_mean)) / cfg.action_std).astype(np.float32))
        losses = []
        for epoch in range(1, int(epochs) + 1):
            t0, total = time.perf_counter(), 0.0
            net.train()
            for b in np.array_split(rng.permutation(n), max(1, int(np.ceil(n / batch_size)))):
                bi = torch.from_numpy(b)
                pred = net(random_shift(x_img[bi], shift_px, gen, torch), x_state[bi])
                loss = torch.nn.functional.mse_loss(pred, y[bi])
                opt.zero_grad()
                loss.backward()
                opt.step()
                total += loss.item() * len(b)
            losses.append(total / n)
            if log is not None:
                log(f"epoch {epoch}/{epochs}: loss {losses[-1]:.4f} ({time.perf_counter() - t0:.1f} s)")
            if epoch in snapshots and on_snapshot is not None:
                on_snapshot(epoch, net, list(losses))
        return net, losses
    finally:
        torch.set_num_threads(old_threads)


# ---- files ------------------------------------------------------------------------------------------------
def save_policy(path: str | Path, cfg: CNNConfig, net) -> Path:
    """Write DIR/config.json and DIR/weights.pt (a state_dict of tensors)."""
    torch = _torch()
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    (path / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    torch.save({k: v.detach().clone() for k, v in net.state_dict().items()}, path / WEIGHTS)
    return path


def load_policy(path: str | Path):
    """(config, network in eval mode) of a checkpoint directory; InputError naming what is missing."""
    torch = _torch()
    path = Path(path)
    if not (path / "config.json").is_file() or not (path / WEIGHTS).is_file():
        raise InputError(f"cnn policy {path}: expected a directory with config.json and {WEIGHTS} "
                         "(written by twinbench.policies.cnn.save_policy)")
    try:
        cfg = CNNConfig.from_dict(json.loads((path / "config.json").read_text()), str(path / "config.json"))
    except (json.JSONDecodeError, TypeError) as err:
        raise InputError(f"cnn policy {path / 'config.json'}: {err}") from None
    net = build_net(cfg)
    try:
        state = torch.load(path / WEIGHTS, map_location="cpu", weights_only=True)
        net.load_state_dict(state)
    except Exception as err:  # noqa: BLE001 - a corrupt or mismatched file is named with its error
        raise InputError(f"cnn policy {path / WEIGHTS}: cannot load the weights for config.json's network "
                         f"({type(err).__name__}: {err})") from None
    return cfg, net.eval()


class CNNPolicy(ChunkedPolicy):
    """A trained CNN policy acting in an env with action bounds `low`, `high`."""

    def __init__(self, cfg: CNNConfig, net, low, high, n_action_steps: int | None = None):
        super().__init__(cfg.n_action_steps if n_action_steps is None else n_action_steps)
        self.cfg, self.net = cfg, net
        self.low, self.high = np.asarray(low, np.float32), np.asarray(high, np.float32)
        if self.low.shape != (cfg.action_dim,):
            raise InputError(f"cnn policy: trained for {cfg.action_dim}-d actions, the env's are "
                             f"{self.low.shape}")

    def predict_chunk(self, obs: dict) -> np.ndarray:
        from twinbench.policies.io import resize_image

        torch = _torch()
        cfg = self.cfg
        try:
            img = obs["pixels"][cfg.camera]
        except KeyError:
            raise PolicyError(f"cnn policy: the observation has no {cfg.camera!r} camera image") from None
        pos = np.asarray(obs["agent_pos"], np.float32)
        img = resize_image(np.asarray(img, np.uint8), (cfg.image_size, cfg.image_size), "stretch")
        state = ((pos[:cfg.state_dim] - np.asarray(cfg.state_mean)) / cfg.state_std).astype(np.float32)
        with torch.no_grad():
            out = self.net(image_tensor(img[None], torch), torch.from_numpy(state)[None])[0].numpy()
        chunk = out * np.asarray(cfg.action_std, np.float32) + np.asarray(cfg.action_mean, np.float32)
        if cfg.relative:
            chunk = chunk + pos[:cfg.action_dim]
        return np.clip(chunk, self.low, self.high).astype(np.float32)


def make_cnn(spec, task, env, *, seed: int):
    """Policy kind `cnn`: `cnn:DIR` (a checkpoint directory of `save_policy`)."""
    cfg, net = load_policy(spec.target)
    return CNNPolicy(cfg, net, env.action_space.low, env.action_space.high, spec.n_action_steps)

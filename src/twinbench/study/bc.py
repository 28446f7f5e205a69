"""The study's vision policies trained by behaviour cloning: demonstrations recorded in the real workcell,
small CNN policies with action chunks (`twinbench.policies.cnn`) trained on them on CPU, several data
sizes and epoch counts so that their real success rates spread.

    specs = make_bc_policies("push-t", REAL / "world", DIR / "policies" / "bc", "small")

Demonstrations: the task's scripted expert in REAL/world (images through the real camera response), from
the task's *sampled* initial states (seeds 10000 + k, never the grid states the study evaluates on), each
executed action perturbed by Gaussian noise (`noise_m`; the label is the expert's clean action, so the
demonstrations show how to recover from small errors, as in DART) and stopped `tail_steps` after success.
Only successful demonstrations are kept. OUT/demos.npz holds the front images downsampled to the
policy's input size, agent_pos and the expert's actions; OUT/demos.json the per-demonstration record.
Checkpoint OUT/bc-d<DEMOS>-e<EPOCHS>/ is a `cnn:` policy directory with train.json (loss per epoch).

With `act=True` / `dp=True` (the lerobot extra), LeRobot ACT / Diffusion Policy policies are trained on the
same demonstrations: LeRobot's own `ACTPolicy` (its loss: L1 on the action chunk + the VAE's KL term) or
`DiffusionPolicy` (noise prediction on the action horizon, conditioned on two observation steps) and
processors (normalisation from the demonstrations' statistics), a random ResNet-18 backbone (nothing is
downloaded), fed by a plain loop instead of `lerobot-train` (the demonstrations are arrays, not a
LeRobotDataset). Checkpoint OUT/act-d<DEMOS>-e<EPOCHS>/ (OUT/dp-...) is a LeRobot `pretrained_model` folder
(config.json, model.safetensors, the processor files) with io.json (the front camera at the training image
size) and train.json, evaluated through the `lerobot:` adapter as any LeRobot checkpoint:
`act-d16-e20=lerobot:DIR?io=DIR/io.json`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinbench._runtime import cpu_cores
from twinbench.errors import InputError

DEMO_SEED = 10000  # demonstrations use sampled initial states from this seed on (the grid states are apart)


@dataclass(frozen=True)
class BCSize:
    """How much a study's behaviour cloning records and trains."""

    demos: int  # demonstrations attempted (the successful ones are kept)
    data_sizes: tuple[int, ...]  # demonstrations per checkpoint (the first N kept)
    epochs: tuple[int, ...]
    lerobot_data_sizes: tuple[int, ...] = (4, 16)  # LeRobot ACT / Diffusion Policy checkpoints
    lerobot_epochs: tuple[int, ...] = (5, 20)
    max_seconds: float = 15.0  # cap on a demonstration's length
    noise_m: float = 0.005
    tail_steps: int = 20


BC_SIZES = {
    "small": BCSize(demos=16, data_sizes=(4, 8, 16), epochs=(5, 40)),
    "medium": BCSize(demos=16, data_sizes=(4, 8, 16), epochs=(5, 40)),  # the small workcell's
    "full": BCSize(demos=48, data_sizes=(6, 16, 48), epochs=(5, 40)),
}


def bc_size(size) -> BCSize:
    if isinstance(size, BCSize):
        return size
    if size not in BC_SIZES:
        raise InputError(f"behaviour cloning size {size!r}: give one of {sorted(BC_SIZES)}")
    return BC_SIZES[size]


def record_demos(task: str, real_world: Path, out: Path, n: int, *, image_size: int = 64,
                 camera: str = "front", max_seconds: float = 15.0, noise_m: float = 0.005,
                 tail_steps: int = 20, seed: int = DEMO_SEED, log=print) -> dict:
    """Record `n` expert demonstrations in `real_world` to OUT/demos.npz (+ demos.json); returns the
    record (per demonstration: seed, steps, success, seconds)."""
    from twinbench.policies.io import resize_image
    from twinbench.tasks import get_task

    spec = get_task(task)
    env = spec.make_env(twin=str(real_world), cameras=camera, environment_state=True,
                        episode_seconds=float(max_seconds))
    expert = spec.make_expert(env)
    low, high = env.action_space.low, env.action_space.high
    images, agent_pos, actions, episode, record = [], [], [], [], []
    t_all = time.perf_counter()
    try:
        for k in range(n):
            t0 = time.perf_counter()
            rng = np.random.default_rng(seed + k)
            obs, info = env.reset(seed=seed + k, options={"sampled": True})
            expert.reset()
            ep_img, ep_pos, ep_act, success_at, steps = [], [], [], None, 0
            while True:
                a = np.asarray(expert.select_action(
                    {**obs, "environment_state": info["privileged"]["environment_state"]}), np.float32)
                ep_img.append(resize_image(obs["pixels"][camera], (image_size, image_size), "stretch"))
                ep_pos.append(np.asarray(obs["agent_pos"], np.float32))
                ep_act.append(a)
                executed = np.clip(a + rng.normal(0.0, noise_m, a.shape), low, high)
                obs, _, term, trunc, info = env.step(executed.astype(np.float32))
                steps += 1
                if info["is_success"] and success_at is None:
                    success_at = steps
                if term or trunc or (success_at is not None and steps >= success_at + tail_steps):
                    break
            ok = success_at is not None
            record.append({"seed": seed + k, "steps": steps, "success": ok, "kept": ok,
                           "seconds": round(time.perf_counter() - t0, 1)})
            if ok:
                images += ep_img
                agent_pos += ep_pos
                actions += ep_act
                episode += [sum(r["kept"] for r in record) - 1] * steps
            log(f"demo {k + 1}/{n} (seed {seed + k}): {steps} steps, success {ok}, "
                f"{record[-1]['seconds']:.0f} s")
    finally:
        env.close()
    if not episode:
        raise RuntimeError(f"behaviour cloning: none of the {n} expert demonstrations in {real_world} "
                           "succeeded; nothing to train on")
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "demos.npz", images=np.stack(images), agent_pos=np.stack(agent_pos),
                        actions=np.stack(actions), episode=np.asarray(episode, np.int32))
    doc = {"task": task, "camera": camera, "image_size": image_size, "noise_m": noise_m,
           "tail_steps": tail_steps, "max_seconds": max_seconds, "demos": record,
           "seconds": round(time.perf_counter() - t_all, 1)}
    (out / "demos.json").write_text(json.dumps(doc, indent=1))
    return doc


def load_demos(out: Path) -> dict[str, np.ndarray]:
    with np.load(out / "demos.npz") as z:
        return {k: z[k] for k in z.files}


def _pending_runs(demos: dict[str, np.ndarray], out: Path, prefix: str, data_sizes, epochs,
                  paths: list[Path]):
    """Per data size N (capped at the demonstrations there are): add its checkpoint folders
    OUT/<prefix>-d<N>-e<E>/ to `paths` and, unless each holds a train.json already, yield (N, {E: folder},
    the first N demonstrations' arrays)."""
    n_kept = int(demos["episode"].max()) + 1
    for d in data_sizes:
        d = min(int(d), n_kept)
        names = {e: out / f"{prefix}-d{d}-e{e}" for e in epochs}
        paths += [p for p in names.values() if p not in paths]
        if all((p / "train.json").is_file() for p in names.values()):
            continue
        keep = demos["episode"] < d
        yield d, names, {k: v[keep] for k, v in demos.items()}


def train_checkpoints(demos: dict[str, np.ndarray], out: Path, data_sizes, epochs, *, seed: int = 0,
                      image_size: int = 64, camera: str = "front", threads: int = 1, log=print) -> list[Path]:
    """Per data size N (the first N demonstrations), one training run of max(epochs) epochs on `threads`
    CPU threads, saving the checkpoint OUT/bc-d<N>-e<E>/ after each E in `epochs`, with train.json (loss
    per epoch, seconds). A data size whose checkpoints all exist is not trained again."""
    from twinbench.policies.cnn import make_config, save_policy, train

    paths: list[Path] = []
    for d, names, data in _pending_runs(demos, out, "bc", data_sizes, epochs, paths):
        cfg = make_config(data["agent_pos"], data["actions"], data["episode"], camera=camera,
                          image_size=image_size)
        t0 = time.perf_counter()

        def snapshot(epoch, net, losses, d=d, data=data, cfg=cfg, names=names, t0=t0):
            record = {"demos": d, "frames": int(len(data["episode"])), "epochs": epoch, "seed": seed,
                      "threads": threads,
                      "loss": losses[-1], "loss_per_epoch": losses,
                      "train_seconds": round(time.perf_counter() - t0, 1)}
            path = save_policy(names[epoch], replace(cfg, extra=record), net)
            (path / "train.json").write_text(json.dumps(record, indent=1))
            log(f"checkpoint {path.name}: {d} demos ({record['frames']} frames), {epoch} epochs, "
                f"loss {losses[-1]:.4f}, {record['train_seconds']:.0f} s")

        train(cfg, data["images"], data["agent_pos"], data["actions"], data["episode"], epochs=max(epochs),
              seed=seed, threads=threads, snapshots=set(epochs), on_snapshot=snapshot)
    return paths


LEROBOT_ARCHS = {"act": "ACT", "dp": "Diffusion Policy"}  # checkpoint prefix -> LeRobot policy


def _lerobot_parts(arch: str):
    """LeRobot's config and policy classes for `arch` (LEROBOT_ARCHS) and the processor factory; InputError
    naming the extra when missing."""
    from twinbench.policies.lerobot_adapter import import_lerobot

    try:
        torch, _, _, make_pre_post_processors = import_lerobot()
        from lerobot.configs.types import FeatureType, PolicyFeature
        if arch == "act":
            from lerobot.policies.act.configuration_act import ACTConfig as Config
            from lerobot.policies.act.modeling_act import ACTPolicy as Policy
        else:
            from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig as Config
            from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy as Policy
    except ImportError as err:
        raise InputError(f"behaviour cloning with LeRobot {LEROBOT_ARCHS[arch]}: {err}") from None
    return torch, make_pre_post_processors, FeatureType, PolicyFeature, Config, Policy


# ACT at a CPU-trainable size: LeRobot's defaults but for the model width and layer counts
ACT_SETTINGS = {"chunk_size": 16, "n_action_steps": 8, "dim_model": 256, "n_heads": 8,
                "dim_feedforward": 1024, "n_encoder_layers": 2, "n_decoder_layers": 1, "latent_dim": 32,
                "n_vae_encoder_layers": 2}
# Diffusion Policy at a CPU-trainable size: LeRobot's defaults but for the U-Net widths, a 16-step horizon
# (the ACT chunk), random 56-pixel crops of the 64-pixel images, group norm (a backbone trained from
# scratch) and DDIM sampling in 10 steps (training keeps the 100-step schedule)
DP_SETTINGS = {"n_obs_steps": 2, "horizon": 16, "n_action_steps": 8, "down_dims": (64, 128, 256),
               "crop_shape": (56, 56), "use_group_norm": True, "noise_scheduler_type": "DDIM",
               "num_inference_steps": 10}
SETTINGS = {"act": ACT_SETTINGS, "dp": DP_SETTINGS}


def train_lerobot_checkpoints(demos: dict[str, np.ndarray], out: Path, data_sizes, epochs, *,
                              arch: str = "act", seed: int = 0, camera: str = "front", threads: int = 1,
                              batch_size: int = 32, lr: float = 1e-4, shift_px: int = 4,
                              settings: dict | None = None, log=print) -> list[Path]:
    """Per data size N (the first N demonstrations), one training run of LeRobot's `arch` policy ("act" or
    "dp", LEROBOT_ARCHS) for max(epochs) epochs, saving OUT/<arch>-d<N>-e<E>/ after each E in `epochs`
    (module docstring); a data size whose checkpoints all exist is not trained again. Seeded: the same
    inputs, seed and `threads` give the same weights. Samples as LeRobot's dataset makes them: ACT sees a
    step's image and state and its next `chunk_size` actions; Diffusion Policy the last `n_obs_steps`
    observations and `horizon` actions from the first of them; steps outside the episode are its first or
    last one repeated (marked as padding). Adam at `lr` (backbone too: it starts random), gradients
    clipped at 10; ACT sees random shifts of up to `shift_px` pixels, Diffusion Policy its own random
    crops."""
    from twinbench.policies.cnn import Adam, episode_window, image_tensor, random_shift

    if arch not in LEROBOT_ARCHS:
        raise InputError(f"LeRobot policy {arch!r}: give one of {sorted(LEROBOT_ARCHS)}")
    torch, make_processors, FeatureType, PolicyFeature, Config, Policy = _lerobot_parts(arch)
    settings = {**SETTINGS[arch], **(settings or {})}
    if arch == "act":
        obs_at, act_at, shift = [0], range(settings["chunk_size"]), shift_px
    else:
        past = settings["n_obs_steps"] - 1
        obs_at, act_at, shift = range(-past, 1), range(-past, settings["horizon"] - past), 0
    size = tuple(int(v) for v in demos["images"].shape[1:3])
    cam = f"observation.images.{camera}"
    paths: list[Path] = []
    for d, names, data in _pending_runs(demos, out, arch, data_sizes, epochs, paths):
        images = image_tensor(data["images"], torch)
        state = torch.from_numpy(np.asarray(data["agent_pos"], np.float32))
        action = torch.from_numpy(np.asarray(data["actions"], np.float32))
        obs_idx = torch.from_numpy(episode_window(data["episode"], obs_at)[0])
        act_idx, act_pad = (torch.from_numpy(a) for a in episode_window(data["episode"], act_at))
        if arch == "act":  # one observation step (no step axis); the loss sees every action (as the CNN's)
            obs_idx, act_pad = obs_idx[:, 0], torch.zeros_like(act_pad)
        n = len(images)

        def stat(x, dims):
            return {"mean": x.mean(dims), "std": x.std(dims).clamp_min(1e-6), "min": x.amin(dims),
                    "max": x.amax(dims)}

        stats = {cam: {k: v[:, None, None] for k, v in stat(images, (0, 2, 3)).items()},
                 "observation.state": stat(state, 0), "action": stat(action, 0)}
        inputs = {cam: PolicyFeature(FeatureType.VISUAL, (3, *size)),
                  "observation.state": PolicyFeature(FeatureType.STATE, (state.shape[1],))}
        lrs = {"optimizer_lr_backbone": lr} if arch == "act" else {}
        cfg = Config(input_features=inputs,
                     output_features={"action": PolicyFeature(FeatureType.ACTION, (action.shape[1],))},
                     pretrained_backbone_weights=None, device="cpu", optimizer_lr=lr, **lrs, **settings)

        old_threads = torch.get_num_threads()
        torch.set_num_threads(int(threads))
        try:
            torch.manual_seed(seed)
            policy = Policy(cfg)
            pre, post = make_processors(cfg, dataset_stats=stats)
            opt = Adam(policy.parameters(), lr=lr)
            gen = torch.Generator().manual_seed(seed)
            rng = np.random.default_rng(seed)
            losses, t0 = [], time.perf_counter()
            for epoch in range(1, max(epochs) + 1):
                policy.train()
                total = 0.0
                for b in np.array_split(rng.permutation(n), max(1, int(np.ceil(n / batch_size)))):
                    bi = torch.from_numpy(b)
                    o = obs_idx[bi]
                    img = random_shift(images[o], shift, gen, torch) if shift else images[o]
                    batch = {cam: img, "observation.state": state[o], "action": action[act_idx[bi]],
                             "action_is_pad": act_pad[bi]}
                    loss, _ = policy.forward(pre(batch))
                    opt.zero_grad()
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
                    opt.step()
                    total += loss.item() * len(b)
                losses.append(total / n)
                if epoch in epochs:
                    record = {"arch": f"lerobot-{arch}", "demos": d, "frames": n, "epochs": epoch,
                              "seed": seed, "threads": threads, "batch_size": batch_size, "lr": lr,
                              "settings": settings,
                              "loss": losses[-1], "loss_per_epoch": list(losses),
                              "train_seconds": round(time.perf_counter() - t0, 1)}
                    _save_lerobot(names[epoch], policy, pre, post, camera, size, record)
                    log(f"checkpoint {names[epoch].name}: {d} demos ({n} frames), {epoch} epochs, "
                        f"loss {losses[-1]:.4f}, {record['train_seconds']:.0f} s")
        finally:
            torch.set_num_threads(old_threads)
    return paths


def _save_lerobot(path: Path, policy, pre, post, camera: str, size: tuple[int, int], record: dict) -> None:
    """The LeRobot folder + io.json + train.json, written beside PATH and renamed into place (a killed
    run leaves no half checkpoint that would be taken as finished)."""
    import shutil

    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    policy.save_pretrained(tmp)
    pre.save_pretrained(tmp)
    post.save_pretrained(tmp)
    io = {"images": {camera: camera}, "image_size": list(size), "resize": "stretch", "prompt": None}
    (tmp / "io.json").write_text(json.dumps(io, indent=1))
    (tmp / "train.json").write_text(json.dumps(record, indent=1))
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)


def lerobot_spec(path: Path) -> str:
    """The policy spec of a checkpoint folder `train_lerobot_checkpoints` wrote."""
    return f"{path.name}=lerobot:{path}?io={path / 'io.json'}"


def make_bc_policies(task: str, real_world: Path, out: Path, size="small", log=print,
                     seed: int = 0, act: bool = False, dp: bool = False) -> list[str]:
    """Record demonstrations in `real_world` (reused when OUT/demos.npz exists), train the size's
    checkpoints into OUT (on min(2, cpu_cores()) threads: the same seed and thread count, the same
    weights) and return their policy specs `bc-d<N>-e<E>=cnn:DIR`, and with `act` / `dp` those of the
    LeRobot ACT / Diffusion Policy checkpoints (module docstring)."""
    bs = bc_size(size)
    out = Path(out)
    if not (out / "demos.npz").is_file():
        t0 = time.perf_counter()
        doc = record_demos(task, real_world, out, bs.demos, max_seconds=bs.max_seconds, noise_m=bs.noise_m,
                           tail_steps=bs.tail_steps, log=log)
        kept = sum(r["kept"] for r in doc["demos"])
        log(f"recorded {kept}/{bs.demos} successful demonstrations in {time.perf_counter() - t0:.0f} s")
    doc, demos = json.loads((out / "demos.json").read_text()), load_demos(out)
    paths = train_checkpoints(demos, out, bs.data_sizes, bs.epochs, seed=seed, image_size=doc["image_size"],
                              camera=doc["camera"], threads=min(2, cpu_cores()), log=log)
    specs = [f"{p.name}=cnn:{p}" for p in paths]
    for arch in [a for a, wanted in (("act", act), ("dp", dp)) if wanted]:
        specs += [lerobot_spec(p) for p in train_lerobot_checkpoints(
            demos, out, bs.lerobot_data_sizes, bs.lerobot_epochs, arch=arch, seed=seed,
            camera=doc["camera"], threads=min(2, cpu_cores()), log=log)]
    return specs

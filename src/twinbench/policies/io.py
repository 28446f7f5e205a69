"""Policy I/O as the policy was trained: what a policy is sent and how its reply becomes env actions.

    io = load_policy_io("openpi-libero")     # a preset name, or a JSON mapping file (same fields)
    request = io.request(obs, prompt)         # env observation -> the policy's input dict
    actions = io.actions(chunk, obs)          # the policy's (T, A) actions -> (T, env action)

A `lerobot:` or `remote:` policy spec picks one with `?io=NAME_OR_FILE` (see `policies.spec`).

Observation (`ObservationMap`; JSON keys in brackets):
- `layout` ["layout"]: "lerobot" = `{"pixels": {name: image}, "agent_pos": state, "prompt": text}` (the
  nested keys LeRobot's gym envs give; other observation entries pass through) or "flat" =
  `{key: image, ..., key: state, prompt_key: text}` and nothing else (openpi). `nested` ["nested"]: top-level
  keys whose "KEY/NAME" entries are gathered into a dict `{KEY: {NAME: ...}}` (ALOHA's `images/cam_high`
  -> `{"images": {"cam_high": ...}}`); other keys keep their slashes (LIBERO's `observation/image`).
- `images` ["images"]: {name or key: camera}; None = every camera under its own name. Each image (HxWx3
  uint8) is cropped to `crop[camera]` = [top, left, height, width] pixels, rotated by 180 degrees for
  cameras in `flip`, then brought to `image_size` = [H, W] by `resize`: "pad" (aspect ratio kept, centred
  on zeros; openpi's `resize_with_pad`), "stretch", or "crop" (centre crop to the aspect, then resize).
  `channels_first` ["channels_first"]: send 3xHxW instead of HxWx3 (ALOHA).
- `state` ["state"]: {key: [part, ...]}, the parts concatenated (float32). Parts read `agent_pos`, whose
  layout is the env's: [x, y, z, qw, qx, qy, qz, gripper] (absolute / relative action modes; gripper
  1 = closed) or [x, y] (planar): "agent_pos" (all), "ee_pos" (3), "ee_quat_wxyz" (4), "ee_quat_xyzw"
  (4), "ee_axis_angle" (3), "gripper" (1), "gripper_fingers" (2: [+w/2, -w/2] with the opening
  w = 0.08 m * (1 - gripper), a LIBERO-style finger qpos derived from the command), "gripper_open" (1:
  1 - gripper, ALOHA's 1 = open), "xy" (2), "zeros:N" (pads a state); any other name is read from the
  observation itself (e.g. "joint_position": the arm's joint angles, "gripper_position"). A part may
  select entries with a slice: "joint_position[0:6]".
- `prompt_key` ["prompt"]: key of the task text (None: not sent).

Actions (`ActionMap`, JSON object "actions"):
- `key` (reply entry, "actions"), `n_action_steps` (actions executed per chunk; None = all or, for
  `lerobot:` policies, the policy's own), `select` (keep these entries, in this order: one arm of a
  bimanual model), `dims` (then keep the first `dims` entries: models that pad),
- `scale` (per-entry multiplier applied first), `gripper` = [lo, hi] (the policy's gripper range, mapped
  linearly to [0, 1], 1 = closed; the last entry),
- `mode`: "absolute" (the result is the env's action) or "chunk_relative": each action is
  [dp (3), dr, g] relative to the end-effector pose (p0, R0 / q0) observed when the chunk was predicted,
  executed as the absolute action [p0 + R0 dp, q0 * dq, g] (env in absolute action mode); `rotation`
  says how dr is written: "axis_angle" (3), "quat_wxyz" or "quat_xyzw" (4).
  Per-step modes convert each action when it is executed, from the observation of that step (for an env
  in absolute action mode, i.e. the gripper tasks):
  - "step_delta" (LIBERO): [dp, dr, g], a delta from the current end-effector pose in the robot's base
    frame (p, R): executed as [p + dp, quat(dR R), g] (dR from dr written as `rotation`).
  - "joint_velocity" (DROID): [v (one per arm joint), g] with v in [-1, 1] (clipped, as openpi's DROID
    example does) the fraction of `joint_delta` rad per step: the joint target `joint_position + v *
    joint_delta` (DROID: 0.2 rad per 15 Hz step = 0.1 rad per 30 Hz env step), whose end-effector pose
    (the env robot's forward kinematics) is executed as the absolute action; the env's controller tracks
    it with its own velocity limits.
  - "joint_position" (ALOHA): [q (k <= arm joints), g], absolute angles of the first k arm joints (the
    others held where they are), executed through their end-effector pose as above.
  `gripper_threshold` (None or t): the gripper command becomes 1 above t, else 0 (DROID: 0.5).
  Joint modes need the env's robot: `make_policy` binds it (`PolicyIO.bind(env)`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from twinbench.transforms import (
    matrix_to_quat,
    matrix_to_rotvec,
    quat_multiply,
    quat_to_matrix,
    rotvec_to_matrix,
)

FINGER_OPENING = 0.08  # m, full opening for the "gripper_fingers" state part
LAYOUTS = ("lerobot", "flat")
RESIZES = ("pad", "stretch", "crop")
MODES = ("absolute", "chunk_relative", "step_delta", "joint_velocity", "joint_position")
STEP_MODES = ("step_delta", "joint_velocity", "joint_position")  # converted per step (`PolicyIO.step`)
ROTATIONS = {"axis_angle": 3, "quat_wxyz": 4, "quat_xyzw": 4}


# ---------------------------------------------------------------- images
def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    from PIL import Image

    if img.shape[:2] == (h, w):
        return img
    return np.asarray(Image.fromarray(img).resize((w, h), resample=Image.BILINEAR))


def resize_image(img: np.ndarray, size: tuple[int, int], mode: str = "pad") -> np.ndarray:
    """HxWx3 uint8 -> size[0] x size[1] x 3 uint8 (modes as in the module docstring)."""
    h, w = int(size[0]), int(size[1])
    ih, iw = img.shape[:2]
    if (ih, iw) == (h, w):
        return img
    if mode == "stretch":
        return _resize(img, h, w)
    if mode == "crop":
        ratio = min(iw / w, ih / h)
        ch, cw = int(round(h * ratio)), int(round(w * ratio))
        top, left = (ih - ch) // 2, (iw - cw) // 2
        return _resize(np.ascontiguousarray(img[top:top + ch, left:left + cw]), h, w)
    ratio = max(iw / w, ih / h)  # "pad"
    rh, rw = int(ih / ratio), int(iw / ratio)
    out = np.zeros((h, w, 3), np.uint8)
    top, left = max(0, (h - rh) // 2), max(0, (w - rw) // 2)
    out[top:top + rh, left:left + rw] = _resize(img, rh, rw)
    return out


# ---------------------------------------------------------------- state
def _ee(agent_pos: np.ndarray, part: str) -> np.ndarray:
    if agent_pos.shape != (8,):
        raise ValueError(f"state part {part!r} needs agent_pos [x, y, z, qw, qx, qy, qz, gripper] (an env "
                         f"in absolute or relative action mode); this env's agent_pos has shape "
                         f"{agent_pos.shape}")
    return agent_pos


def state_part(obs: dict, part: str) -> np.ndarray:
    """One named state part (module docstring) of an env observation, float64."""
    name, bracket, sel = part.partition("[")
    if bracket:
        if not sel.endswith("]"):
            raise ValueError(f"state part {part!r}: write a selection as NAME[start:stop]")
        values = state_part(obs, name)
        try:
            bounds = [int(v) if v.strip() else None for v in sel[:-1].split(":")]
        except ValueError:
            raise ValueError(f"state part {part!r}: write a selection as NAME[start:stop]") from None
        if len(bounds) != 2:
            raise ValueError(f"state part {part!r}: write a selection as NAME[start:stop]")
        out = values[slice(*bounds)]
        if len(out) == 0:
            raise ValueError(f"state part {part!r}: selects nothing of {name}'s {len(values)} entries")
        return out
    a = np.asarray(obs["agent_pos"], np.float64).reshape(-1)
    if part == "agent_pos":
        return a
    if part == "xy":
        return a[:2]
    if part.startswith("zeros:"):
        return np.zeros(int(part.split(":", 1)[1]))
    if part == "ee_pos":
        return _ee(a, part)[:3]
    if part == "ee_quat_wxyz":
        return _ee(a, part)[3:7]
    if part == "ee_quat_xyzw":
        return _ee(a, part)[[4, 5, 6, 3]]
    if part == "ee_axis_angle":
        return matrix_to_rotvec(quat_to_matrix(_ee(a, part)[3:7]))
    if part == "gripper":
        return _ee(a, part)[7:8]
    if part == "gripper_open":
        return 1.0 - _ee(a, part)[7:8]
    if part == "gripper_fingers":
        half = 0.5 * FINGER_OPENING * (1.0 - float(np.clip(_ee(a, part)[7], 0.0, 1.0)))
        return np.array([half, -half])
    if part in obs:
        return np.asarray(obs[part], np.float64).reshape(-1)
    raise ValueError(f"state part {part!r}: not a known part and not in the observation (keys "
                     f"{sorted(obs)}); known parts: agent_pos, xy, ee_pos, ee_quat_wxyz, ee_quat_xyzw, "
                     f"ee_axis_angle, gripper, gripper_open, gripper_fingers, zeros:N, NAME[start:stop]")


# ---------------------------------------------------------------- maps
@dataclass(frozen=True)
class ObservationMap:
    layout: str = "lerobot"
    images: dict[str, str] | None = None
    image_size: tuple[int, int] | None = None
    resize: str = "pad"
    crop: dict[str, tuple[int, int, int, int]] = field(default_factory=dict)
    flip: tuple[str, ...] = ()
    state: dict[str, tuple[str, ...]] = field(default_factory=lambda: {"agent_pos": ("agent_pos",)})
    prompt_key: str | None = "prompt"
    nested: tuple[str, ...] = ()
    channels_first: bool = False

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {LAYOUTS}, got {self.layout!r}")
        if self.resize not in RESIZES:
            raise ValueError(f"resize: expected one of {RESIZES}, got {self.resize!r}")
        if self.image_size is not None and (len(self.image_size) != 2 or min(self.image_size) < 1):
            raise ValueError(f"image_size: expected [height, width] >= 1, got {self.image_size}")
        for cam, box in self.crop.items():
            if len(box) != 4 or box[2] < 1 or box[3] < 1 or box[0] < 0 or box[1] < 0:
                raise ValueError(f"crop[{cam!r}]: expected [top, left, height, width], got {box}")

    def image(self, obs: dict, camera: str) -> np.ndarray:
        pixels = obs["pixels"]
        if camera not in pixels:
            raise ValueError(f"images: camera {camera!r} is not in the observation "
                             f"(cameras {sorted(pixels)})")
        img = np.asarray(pixels[camera])
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"pixels[{camera!r}] must be HxWx3 uint8, got {img.shape} {img.dtype}")
        if camera in self.crop:
            top, left, h, w = (int(v) for v in self.crop[camera])
            if top + h > img.shape[0] or left + w > img.shape[1]:
                raise ValueError(f"crop[{camera!r}] = {self.crop[camera]} exceeds the {img.shape[:2]} image")
            img = img[top:top + h, left:left + w]
        if camera in self.flip:
            img = img[::-1, ::-1]
        img = np.ascontiguousarray(img)
        img = img if self.image_size is None else resize_image(img, self.image_size, self.resize)
        return np.ascontiguousarray(img.transpose(2, 0, 1)) if self.channels_first else img

    def request(self, obs: dict, prompt: str | None) -> dict:
        images = self.images if self.images is not None else {c: c for c in obs["pixels"]}
        imgs = {key: self.image(obs, cam) for key, cam in images.items()}
        states = {key: np.concatenate([state_part(obs, p) for p in parts]).astype(np.float32)
                  for key, parts in self.state.items()}
        if self.layout == "lerobot":  # other observation entries (depth, environment_state) pass through
            out: dict = {**{k: v for k, v in obs.items() if k != "pixels"}, "pixels": imgs, **states}
        else:
            out = {**imgs, **states}
        if self.prompt_key is not None and prompt is not None:
            out[self.prompt_key] = prompt
        for top in self.nested:
            inner = {k[len(top) + 1:]: out.pop(k) for k in list(out) if k.startswith(top + "/")}
            if top in out:
                raise ValueError(f"nested: {top!r} is both a key and the prefix of {sorted(inner)}")
            out[top] = inner
        return out


@dataclass(frozen=True)
class ActionMap:
    key: str = "actions"
    n_action_steps: int | None = None
    dims: int | None = None
    scale: tuple[float, ...] | None = None
    gripper: tuple[float, float] | None = None
    mode: str = "absolute"
    rotation: str = "axis_angle"
    select: tuple[int, ...] | None = None
    gripper_threshold: float | None = None
    joint_delta: float = 0.1  # rad per step at |v| = 1 ("joint_velocity")

    def __post_init__(self) -> None:
        if self.select is not None and (len(self.select) == 0 or min(self.select) < 0):
            raise ValueError(f"actions.select: expected entry indices >= 0, got {self.select}")
        if not self.joint_delta > 0:
            raise ValueError(f"actions.joint_delta: must be > 0, got {self.joint_delta}")
        if self.mode not in MODES:
            raise ValueError(f"actions.mode: expected one of {MODES}, got {self.mode!r}")
        if self.rotation not in ROTATIONS:
            raise ValueError(f"actions.rotation: expected one of {sorted(ROTATIONS)}, got {self.rotation!r}")
        if self.n_action_steps is not None and int(self.n_action_steps) < 1:
            raise ValueError(f"actions.n_action_steps: must be >= 1 or null, got {self.n_action_steps}")
        if self.gripper is not None and (len(self.gripper) != 2 or self.gripper[0] == self.gripper[1]):
            raise ValueError(f"actions.gripper: expected [lo, hi] with lo != hi, got {self.gripper}")

    def actions(self, chunk, obs: dict) -> np.ndarray:
        a = np.asarray(chunk, np.float64)
        a = a[None] if a.ndim == 1 else a
        if a.ndim != 2 or len(a) == 0:
            raise ValueError(f"actions: expected a (T, A) chunk, got shape {a.shape}")
        if self.select is not None:
            if max(self.select) >= a.shape[1]:
                raise ValueError(f"actions.select = {list(self.select)} but the policy's actions have "
                                 f"{a.shape[1]} entries")
            a = a[:, list(self.select)]
        if self.dims is not None:
            if a.shape[1] < self.dims:
                raise ValueError(f"actions.dims = {self.dims} but the policy's actions have "
                                 f"{a.shape[1]} entries")
            a = a[:, :self.dims]
        if self.scale is not None:
            if len(self.scale) != a.shape[1]:
                raise ValueError(f"actions.scale has {len(self.scale)} entries for {a.shape[1]}-d actions")
            a = a * np.asarray(self.scale)
        if self.gripper is not None:
            lo, hi = self.gripper
            a = a.copy()
            a[:, -1] = np.clip((a[:, -1] - lo) / (hi - lo), 0.0, 1.0)
        if self.gripper_threshold is not None:
            a = a.copy()
            a[:, -1] = (a[:, -1] > self.gripper_threshold).astype(np.float64)
        if self.mode == "chunk_relative":
            a = self._compose(a, np.asarray(obs["agent_pos"], np.float64).reshape(-1))
        return a.astype(np.float32)

    def step(self, action, obs: dict, robot=None) -> np.ndarray:
        """One action of a per-step mode (module docstring) -> the env's absolute action, from `obs` (the
        observation of the step it is executed at); other modes return it unchanged."""
        a = np.asarray(action, np.float64).reshape(-1)
        if self.mode not in STEP_MODES:
            return np.asarray(action, np.float32)
        if self.mode == "step_delta":
            k = ROTATIONS[self.rotation]
            if a.shape != (3 + k + 1,):
                raise ValueError(f"step_delta actions with {self.rotation} rotations have {3 + k + 1} "
                                 f"entries [dp, dr, gripper], got {a.shape[0]}")
            pose = _ee(np.asarray(obs["agent_pos"], np.float64).reshape(-1), "step_delta")
            dr = a[3:3 + k]
            if self.rotation == "axis_angle":
                rot = rotvec_to_matrix(dr)
            else:
                dq = dr if self.rotation == "quat_wxyz" else dr[[3, 0, 1, 2]]
                rot = quat_to_matrix(dq / np.linalg.norm(dq))
            q = matrix_to_quat(rot @ quat_to_matrix(pose[3:7] / np.linalg.norm(pose[3:7])))  # w >= 0
            return np.concatenate([pose[:3] + a[:3], q, a[-1:]]).astype(np.float32)
        if robot is None:
            raise ValueError(f"actions.mode {self.mode!r} needs the env's robot (PolicyIO.bind(env))")
        if "joint_position" not in obs:
            raise ValueError(f"actions.mode {self.mode!r} needs 'joint_position' in the observation "
                             f"(keys {sorted(obs)})")
        q_arm = np.asarray(obs["joint_position"], np.float64).reshape(-1)
        n = len(q_arm)
        if self.mode == "joint_velocity":
            if a.shape != (n + 1,):
                raise ValueError(f"joint_velocity actions have {n + 1} entries (one per arm joint + gripper) "
                                 f"for this robot, got {a.shape[0]}")
            target = q_arm + np.clip(a[:n], -1.0, 1.0) * self.joint_delta
        else:
            if not 2 <= a.shape[0] <= n + 1:
                raise ValueError(f"joint_position actions have 1 to {n} joint angles + gripper for this "
                                 f"robot, got {a.shape[0]} entries")
            target = q_arm.copy()
            target[:a.shape[0] - 1] = a[:-1]
        q = robot.home_q.copy()
        q[robot.arm_q_indices] = target
        pose = robot.ee_pose(robot.clip_q(q))
        return np.concatenate([pose[:3, 3], matrix_to_quat(pose[:3, :3]), a[-1:]]).astype(np.float32)

    def _compose(self, a: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        """[dp, dr, g] relative to the chunk's first pose -> absolute [p0 + R0 dp, q0 * dq, g]."""
        k = ROTATIONS[self.rotation]
        if a.shape[1] != 3 + k + 1:
            raise ValueError(f"chunk_relative actions with {self.rotation} rotations have {3 + k + 1} "
                             f"entries [dp, dr, gripper], got {a.shape[1]}")
        p0, q0 = _ee(agent_pos, "chunk_relative")[:3], agent_pos[3:7] / np.linalg.norm(agent_pos[3:7])
        r0 = quat_to_matrix(q0)
        dr = a[:, 3:3 + k]
        if self.rotation == "axis_angle":
            dq = matrix_to_quat(rotvec_to_matrix(dr))
        else:
            dq = dr if self.rotation == "quat_wxyz" else dr[:, [3, 0, 1, 2]]
            dq = dq / np.linalg.norm(dq, axis=1, keepdims=True)
        q = quat_multiply(q0[None], dq)
        q = q * np.where(q[:, :1] < 0, -1.0, 1.0)  # w >= 0 (same rotation)
        return np.concatenate([p0 + a[:, :3] @ r0.T, q, a[:, -1:]], axis=1)


@dataclass(frozen=True)
class PolicyIO:
    """An observation map and an action map (see the module docstring)."""

    name: str = "lerobot"
    observation: ObservationMap = field(default_factory=ObservationMap)
    action: ActionMap = field(default_factory=ActionMap)
    robot: object = field(default=None, compare=False, repr=False)  # the env's RobotModel (joint modes)

    def request(self, obs: dict, prompt: str | None = None) -> dict:
        return self.observation.request(obs, prompt)

    def actions(self, chunk, obs: dict) -> np.ndarray:
        return self.action.actions(chunk, obs)

    def step(self, action, obs: dict) -> np.ndarray:
        """The env action of one queued action at the step it is executed (per-step modes)."""
        return self.action.step(action, obs, self.robot)

    def bind(self, env) -> PolicyIO:
        """This io with `env`'s robot (what the joint action modes execute through)."""
        twin = getattr(getattr(env, "unwrapped", env), "twin", None)
        return replace(self, robot=getattr(twin, "robot", None))

    def with_n_action_steps(self, n: int | None) -> PolicyIO:
        return self if n is None else replace(self, action=replace(self.action, n_action_steps=int(n)))


_OPENPI_IMAGE = {"layout": "flat", "image_size": (224, 224), "resize": "pad"}
PRESETS: dict[str, PolicyIO] = {
    # LeRobot gym-env keys at the camera's own size; the policy's actions are the env's.
    "lerobot": PolicyIO("lerobot"),
    # openpi LIBERO models (pi0 / pi0-FAST / pi05 _libero): 224x224 padded images, state = end-effector
    # position + axis-angle + finger qpos (8), per-step actions [dp, d axis-angle, gripper in [-1, 1]]
    # (7 of the reply's entries) in the base frame as normalised by LIBERO's OSC controller (x 0.05 m,
    # x 0.5 rad), executed from each step's pose; 5 actions per chunk (openpi's LIBERO example replans
    # every 5 steps).
    "openpi-libero": PolicyIO("openpi-libero", ObservationMap(
        images={"observation/image": "front", "observation/wrist_image": "wrist"},
        state={"observation/state": ("ee_pos", "ee_axis_angle", "gripper_fingers")}, **_OPENPI_IMAGE),
        ActionMap(n_action_steps=5, dims=7, scale=(0.05,) * 3 + (0.5,) * 3 + (1.0,), gripper=(-1.0, 1.0),
                  mode="step_delta")),
    # openpi DROID models: 224x224 padded exterior + wrist images, 7 joint positions + gripper position
    # (1 = closed); replies (10, 8) = 7 joint velocities in [-1, 1] + gripper position, binarised at 0.5
    # and executed as DROID's joint-velocity controller would (module docstring); 8 per chunk (openpi's
    # open-loop horizon).
    "openpi-droid": PolicyIO("openpi-droid", ObservationMap(
        images={"observation/exterior_image_1_left": "front", "observation/wrist_image_left": "wrist"},
        state={"observation/joint_position": ("joint_position",),
               "observation/gripper_position": ("gripper_position",)},
        **_OPENPI_IMAGE), ActionMap(n_action_steps=8, dims=8, gripper_threshold=0.5, mode="joint_velocity")),
    # openpi ALOHA models (bimanual, 14-d: per arm 6 joints + gripper, 1 = open): the twin's arm is sent as
    # the left arm (its first 6 joints, the right arm zeros), images as the nested dict `images` of 3x224x224
    # (cam_high = front, cam_left_wrist = wrist; openpi fills the missing cameras); replies (50, 14) of
    # absolute joint angles: the left arm's 7 entries drive the first 6 joints + gripper; 25 per chunk
    # (openpi's ALOHA example).
    "openpi-aloha": PolicyIO("openpi-aloha", ObservationMap(
        images={"images/cam_high": "front", "images/cam_left_wrist": "wrist"}, nested=("images",),
        channels_first=True, state={"state": ("joint_position[0:6]", "gripper_open", "zeros:7")},
        **_OPENPI_IMAGE), ActionMap(n_action_steps=25, select=tuple(range(7)), gripper=(1.0, 0.0),
                                    mode="joint_position")),
    # A policy trained on the reference cell's recordings: end-effector deltas relative to the pose at the
    # chunk's start ([dp, axis-angle, gripper]), executed as absolute targets.
    "chunk-relative": PolicyIO("chunk-relative", ObservationMap(),
                               ActionMap(mode="chunk_relative", rotation="axis_angle")),
}


def _tuples(value):
    return tuple(value) if isinstance(value, list) else value


def policy_io_from_dict(data: dict, name: str = "file") -> PolicyIO:
    """A PolicyIO from a JSON-style dict (module docstring); unknown keys are errors."""
    obs_keys = {"layout", "images", "image_size", "resize", "crop", "flip", "state", "prompt", "nested",
                "channels_first"}
    unknown = sorted(set(data) - obs_keys - {"actions", "preset"})
    if unknown:
        known = sorted(obs_keys | {"actions", "preset"})
        raise ValueError(f"policy io {name}: unknown key(s) {unknown}; known: {known}")
    if "preset" in data and data["preset"] not in PRESETS:
        raise ValueError(f"policy io {name}: unknown preset {data['preset']!r}; presets: {sorted(PRESETS)}")
    base = PRESETS[data["preset"]] if "preset" in data else PolicyIO(name)
    obs_kw = {("prompt_key" if k == "prompt" else k): v for k, v in data.items() if k in obs_keys}
    if "image_size" in obs_kw and obs_kw["image_size"] is not None:
        obs_kw["image_size"] = tuple(int(v) for v in obs_kw["image_size"])
    if "crop" in obs_kw:
        obs_kw["crop"] = {cam: tuple(int(v) for v in box) for cam, box in obs_kw["crop"].items()}
    for key in ("flip", "nested"):
        if key in obs_kw:
            obs_kw[key] = tuple(obs_kw[key])
    if "state" in obs_kw:
        obs_kw["state"] = {k: tuple(v) for k, v in obs_kw["state"].items()}
    act = dict(data.get("actions") or {})
    act_fields = {f.name for f in fields(ActionMap)}
    bad = sorted(set(act) - act_fields)
    if bad:
        raise ValueError(f"policy io {name}: unknown actions key(s) {bad}; known: {sorted(act_fields)}")
    act = {k: _tuples(v) for k, v in act.items()}
    return PolicyIO(name, replace(base.observation, **obs_kw), replace(base.action, **act))


def load_policy_io(spec: str | PolicyIO | None) -> PolicyIO:
    """A preset name (`lerobot`, `openpi-libero`, `openpi-droid`, `openpi-aloha`, `chunk-relative`) or a
    JSON file."""
    if spec is None or spec == "":
        return PRESETS["lerobot"]
    if isinstance(spec, PolicyIO):
        return spec
    if spec in PRESETS:
        return PRESETS[spec]
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"policy io {spec!r}: neither a preset ({', '.join(sorted(PRESETS))}) "
                         "nor a JSON file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"policy io file {path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"policy io file {path}: expected a JSON object")
    try:
        return policy_io_from_dict(data, name=path.stem)
    except (TypeError, ValueError) as err:
        raise ValueError(f"policy io file {path}: {err}") from None

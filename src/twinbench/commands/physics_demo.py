"""`twinbench physics-demo`: a soft cube dropped, squeezed by two fingers and lifted.

Grasping is pure friction: the fingers close until the contact force on both exceeds a threshold
(latch), then lift and hold. Writes ``physics_demo.png`` (snapshots, COM height and finger force
curves) and ``physics_demo.mp4`` (orthographic side view) into ``out_dir``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the physics demo (defaults take well under 2 minutes on a 2-core CPU)."""

    out_dir: Path = Path("outputs")
    device: str = "cpu"
    cube_size: int = 6
    """particles per cube edge (1 cm spacing)"""
    drop_height: float = 0.08
    """height of the cube's lowest particles at release, m"""
    settle_frames: int = 30
    """frames (30 Hz) to fall and settle before the fingers close"""
    close_speed: float = 0.06
    """finger closing speed, m/s"""
    latch_force: float = 2000.0
    """per-finger inward contact force that latches the gripper (N, unit particle masses)"""
    lift_speed: float = 0.1
    """m/s"""
    lift_height: float = 0.08
    """m"""
    hold_frames: int = 30
    """frames held in the air after the lift (30 = 1 s)"""
    max_close_frames: int = 30
    """error out if the latch force is not reached within this many frames"""
    video: bool = True
    """also write physics_demo.mp4"""
    fps: int = 30
    spring_Y: float = 3e4
    """spring stiffness (per unit strain)"""
    friction: float = 1.0
    """finger friction coefficient (grasping is friction only)"""


def simulate(cfg: DemoConfig) -> dict:
    """Run the scenario; returns per-frame particle positions, finger boxes, COM height and forces."""
    import trimesh

    from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
    from twinbench.physics.model import lattice

    p = SimParams(ground_restitution=0.3, ground_friction=0.5)
    b = ModelBuilder(p)
    n = cfg.cube_size
    half = (n - 1) * 0.01 / 2
    pts = lattice(n, n, n, 0.01, origin=(-half, -half, cfg.drop_height))  # centred on the z axis
    b.add_body(pts, spring_Y=cfg.spring_Y)
    size = 2 * half + 0.01
    finger = trimesh.creation.box(extents=(0.01, size, size))
    gap = half + p.mesh_margin + 0.01
    verts = [np.asarray(finger.vertices) + (s * (gap + 0.005), 0.0, size / 2) for s in (-1, 1)]
    ids = [b.add_kinematic_mesh(v, finger.faces, restitution=0.0, friction=cfg.friction) for v in verts]
    model = b.finalize(cfg.device)
    solver = SpringMassSolver(model)
    state, ctl = model.state(), model.control()
    fdt = p.frame_dt
    lift_frames = int(round(cfg.lift_height / (cfg.lift_speed * fdt)))
    xs, fingers, com, force, phase = [], [], [], [], []
    latched_at = None
    k = 0
    while True:
        if k < cfg.settle_frames:
            ph, nxt = "settle", verts
        elif latched_at is None:
            ph = "close"
            d = cfg.close_speed * fdt
            nxt = [verts[0] + (d, 0, 0), verts[1] - (d, 0, 0)]
            if k - cfg.settle_frames >= cfg.max_close_frames:
                raise RuntimeError("demo: the fingers never reached the latch force; raise max_close_frames")
        elif k - latched_at <= lift_frames:
            ph, nxt = "lift", [v + (0, 0, cfg.lift_speed * fdt) for v in verts]
        elif k - latched_at <= lift_frames + cfg.hold_frames:
            ph, nxt = "hold", verts
        else:
            break
        for mid, a, c in zip(ids, verts, nxt, strict=True):
            ctl.set_kinematic_mesh(mid, a, c)
        solver.simulate_frame(state, ctl)
        verts = nxt
        f = [solver.mesh_contact_force(mid) for mid in ids]
        if ph == "close" and f[0][0] > cfg.latch_force and f[1][0] < -cfg.latch_force:
            latched_at = k
        x = state.x.numpy()
        xs.append(x)
        fingers.append([v.copy() for v in verts])
        com.append(float(x[:, 2].mean()))
        force.append((float(f[0][0]), float(-f[1][0]), float(f[0][2] + f[1][2])))
        phase.append(ph)
        k += 1
    t = (np.arange(len(com)) + 1) * fdt
    return {"t": t, "x": np.asarray(xs), "fingers": fingers, "com_z": np.asarray(com),
            "force": np.asarray(force), "phase": phase, "latched_frame": latched_at,
            "weight": float(model.masses_np.sum() * 9.8), "x0": pts}


def _render(x: np.ndarray, fingers: list[np.ndarray], w: int = 320, h: int = 240) -> np.ndarray:
    """Orthographic side view (x right, z up) as an HxWx3 uint8 image; particles shaded by depth (y)."""
    img = np.full((h, w, 3), 245, np.uint8)
    scale = w / 0.3  # 30 cm across
    cx, gz = w / 2, h - 20
    img[gz:, :] = (200, 190, 170)  # ground

    def px(points):
        return (cx + points[:, 0] * scale).astype(int), (gz - points[:, 2] * scale).astype(int)

    for f in fingers:
        u, v = px(f)
        img[max(v.min(), 0):max(v.max(), 0), max(u.min(), 0):max(u.max(), 0)] = (90, 90, 100)
    order = np.argsort(-x[:, 1])  # far first
    u, v = px(x[order])
    depth = (x[order, 1] - x[:, 1].min()) / max(np.ptp(x[:, 1]), 1e-6)
    r = 3
    for du in range(-r, r + 1):
        for dv in range(-r, r + 1):
            if du * du + dv * dv > r * r:
                continue
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            shade = (1.0 - 0.5 * depth[ok])[:, None]
            img[vv[ok], uu[ok]] = (shade * np.array([220, 60, 50])).astype(np.uint8)
    return img


def write_outputs(res: dict, cfg: DemoConfig) -> tuple[Path, Path | None]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = len(res["com_z"])
    snaps = sorted({0, n // 3, (2 * n) // 3, n - 1})
    fig = plt.figure(figsize=(12, 6.5))
    for i, k in enumerate(snaps):
        ax = fig.add_subplot(2, len(snaps), i + 1)
        ax.imshow(_render(res["x"][k], res["fingers"][k]))
        ax.set_title(f"t = {res['t'][k]:.2f} s ({res['phase'][k]})")
        ax.axis("off")
    ax = fig.add_subplot(2, 2, 3)
    ax.plot(res["t"], res["com_z"] * 100)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("cube COM height [cm]")
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 2, 4)
    ax.plot(res["t"], res["force"][:, 0], label="left finger, inward")
    ax.plot(res["t"], res["force"][:, 1], label="right finger, inward")
    ax.plot(res["t"], res["force"][:, 2], label="both, vertical (friction)")
    ax.axhline(res["weight"], color="k", ls=":", label="cube weight")
    if res["latched_frame"] is not None:
        ax.axvline(res["t"][res["latched_frame"]], color="r", ls="--", label="latched")
    ax.set_yscale("symlog", linthresh=100.0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("mean contact force per frame [N]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    png = out / "physics_demo.png"
    fig.savefig(png, dpi=100)
    plt.close(fig)
    mp4 = None
    if cfg.video:
        import imageio.v2 as imageio

        mp4 = out / "physics_demo.mp4"
        with imageio.get_writer(mp4, fps=cfg.fps, codec="libx264", macro_block_size=8) as wr:
            for k in range(n):
                wr.append_data(_render(res["x"][k], res["fingers"][k]))
    return png, mp4


def main(cfg: DemoConfig) -> int:
    t0 = time.perf_counter()
    res = simulate(cfg)
    png, mp4 = write_outputs(res, cfg)
    rest = res["com_z"][max(cfg.settle_frames - 1, 0)]
    lifted = res["com_z"][-1] - rest
    print(f"simulated {len(res['com_z'])} frames in {time.perf_counter() - t0:.1f} s "
          f"(latched at frame {res['latched_frame']}, cube COM {lifted * 100:.1f} cm above its rest height)")
    print(f"wrote {png}")
    if mp4 is not None:
        print(f"wrote {mp4}")
    return 0

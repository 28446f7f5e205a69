"""Spring-mass solver speed and memory on rope-sized and plush-toy-sized models.

Prints `name value unit` lines, per device (`cpu`, and `cuda:0` when present) and model:
- substeps per second and ms per 30 Hz frame (667 substeps), median of timed frames after warm-up,
  with self-collision on (two bodies, candidates rebuilt every frame);
- the same with one kinematic mesh (a finger pushing into the body: per-substep vertex
  interpolation and BVH refit, no graph capture);
- peak resident memory of the process (MiB) after the model's runs;
- one world on two CPU cores (each frame split with a helper process, bit-identical): ms per frame
  (the lines above are one core), and two worlds of one model on 1 and 2 threads (ms per world-frame);
- a heavy kinematic mesh (a CAD-like 20,480-face ball as the finger, rope-sized model, CPU) against its
  simplified convex hull (`robot.contact_mesh: "convex_hull"`): ms per frame of each.

Usage: python benchmarks/physics.py [--device cpu|cuda:0|all] [--frames N]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

import numpy as np
import trimesh
import warp as wp

from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.physics.model import lattice

MODELS = {
    # name: two bodies (main body + a small cube resting on it), self-collision on
    "rope": dict(shape=(250, 3, 2), spacing=0.004, radius=0.008),  # 1,500 particles, 1 m long
    "plush": dict(shape=(15, 15, 14), spacing=0.01, radius=0.02),  # 3,150 particles, ~40k springs
}


def _build(name: str, device: str, with_mesh: bool, num_worlds: int = 1, finger=None):
    spec = MODELS[name]
    s = spec["spacing"]
    body = lattice(*spec["shape"], s, (0.0, 0.0, 0.0))
    top = body[:, 2].max()
    p = SimParams(collision_dist=1.5 * s, self_collision=True)
    b = ModelBuilder(p)
    b.add_body(body, radius=spec["radius"], max_neighbors=30)
    b.add_body(lattice(3, 3, 3, s, (0.0, 0.0, top + 1.2 * s)), radius=spec["radius"])
    mesh = None
    if with_mesh:
        box = trimesh.creation.box(extents=(0.02, 0.02, 0.02)) if finger is None else finger
        verts = np.asarray(box.vertices) + (-0.0105 - 0.002, 0.01, 0.01)
        mesh = (b.add_kinematic_mesh(verts, box.faces, restitution=0.0, friction=0.5), verts)
    model = b.finalize(device, num_worlds=num_worlds)
    return model, mesh


def _time_frames(model, mesh, frames: int, threads: int | None = None) -> list[float]:
    solver = SpringMassSolver(model, threads=1 if threads is None else threads)
    state, ctl = model.state(), model.control()
    times = []
    verts = mesh[1] if mesh else None
    for k in range(frames + 2):  # 2 warm-up frames (graph capture, first launches)
        if mesh:
            nxt = verts + (0.05 * model.params.frame_dt, 0.0, 0.0)  # push at 5 cm/s
            ctl.set_kinematic_mesh(mesh[0], verts, nxt)
            verts = nxt
        wp.synchronize_device(model.device)
        t0 = time.perf_counter()
        solver.simulate_frame(state, ctl, check=False)
        wp.synchronize_device(model.device)
        if k >= 2:
            times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="all")
    ap.add_argument("--frames", type=int, default=5)
    args = ap.parse_args()
    wp.init()
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    if args.device != "all":
        devices = [args.device]
    for dev in devices:
        tag = "cpu" if dev == "cpu" else "cuda"
        for name in MODELS:
            for with_mesh in (False, True):
                model, mesh = _build(name, dev, with_mesh)
                if not with_mesh:
                    print(f"physics_{name}_particles {model.num_particles} count")
                    print(f"physics_{name}_springs {model.num_springs} count")
                med = statistics.median(_time_frames(model, mesh, args.frames))
                sub = model.params.substeps
                suffix = "_kinematic_mesh" if with_mesh else ""
                print(f"physics_{name}_{tag}{suffix}_ms_per_frame {med * 1e3:.1f} ms")
                print(f"physics_{name}_{tag}{suffix}_substeps_per_s {sub / med:.0f} substeps/s")
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            print(f"physics_{name}_{tag}_peak_rss {rss:.0f} MiB")
            if dev == "cpu":
                for with_mesh in (False, True):
                    model, mesh = _build(name, dev, with_mesh)
                    med = statistics.median(_time_frames(model, mesh, args.frames, threads=2))
                    suffix = "_kinematic_mesh" if with_mesh else ""
                    print(f"physics_{name}_cpu{suffix}_2cores_ms_per_frame {med * 1e3:.1f} ms")
                model, _ = _build(name, dev, False, num_worlds=2)
                for threads in (1, 2):
                    med = statistics.median(_time_frames(model, None, args.frames, threads=threads))
                    label = f"physics_{name}_cpu_2worlds_{threads}threads"
                    print(f"{label}_ms_per_world_frame {med * 1e3 / 2:.1f} ms")
        if dev == "cpu":
            _heavy_mesh(args.frames)


def _heavy_mesh(frames: int) -> None:
    """The rope-sized model pushed by a 20,480-face ball and by its simplified convex hull."""
    from twinbench.robot.model import convex_contact_mesh

    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.01)
    hull, moved = convex_contact_mesh(ball)
    print(f"physics_heavy_mesh_hull_faces {len(hull.faces)} count ({len(ball.faces)} in the mesh; "
          f"the hull within {moved * 1e3:.2f} mm)")
    for label, finger in (("mesh", ball), ("convex_hull", hull)):
        model, mesh = _build("rope", "cpu", True, finger=finger)
        med = statistics.median(_time_frames(model, mesh, frames))
        print(f"physics_rope_cpu_heavy_{label}_ms_per_frame {med * 1e3:.1f} ms")

if __name__ == "__main__":
    main()

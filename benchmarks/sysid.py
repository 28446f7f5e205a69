"""System identification speed and accuracy on the synthetic rope (hidden soft / stiff halves).

Prints `name value unit` lines:
- seconds per stage-2 iteration (one taped frame forward + backward + Adam step) for the rope, at the
  tests' 40 substeps per frame and at PhysTwin's 667 (dt = 5e-5), per device (`cpu`, and `cuda:0`
  when present), median over timed frames after warm-up;
- seconds per stage-1 evaluation (the training frames simulated on the fast path);
- the tracking error on the held-out validation frames after stage 1 (best single global stiffness)
  and after stage 2, and the rank correlation of per-spring stiffness with the hidden truth (CPU run
  of the whole identification, 40 substeps per frame).

Usage: python benchmarks/sysid.py [--device cpu|cuda:0|all] [--budget N] [--epochs N]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np
import warp as wp
from scipy.stats import spearmanr

from twinbench.construct.sysid_synthetic import synthetic_case
from twinbench.physics import SimParams, SpringMassSolver
from twinbench.physics.sysid import (
    AdamConfig,
    CMAConfig,
    FitConfig,
    GlobalParams,
    SequenceLoss,
    build_model,
    evaluate,
    frame_gradient,
    identify,
)

SEARCH = ("spring_Y", "control_radius", "control_max_neighbors", "ground_restitution", "ground_friction",
          "drag_damping", "dashpot_damping")


def _seconds_per_iteration(data, truth, substeps: int, device: str, frames: int) -> float:
    base = SimParams(dt=1.0 / (30 * substeps), substeps=substeps)
    model = build_model(data, replace(truth["params"], spring_Y=1000.0), base, device, requires_grad=True)
    solver = SpringMassSolver(model)
    ctl = model.control()
    loss = SequenceLoss(data)
    state = model.state()
    prev_v, prev_acc = np.zeros((model.num_particles, 3)), None
    times = []
    for k in range(1, frames + 3):  # 2 warm-up frames
        ctl.set_control_points(data.controls[k - 1], data.controls[k])
        t0 = time.perf_counter()
        _, g, x, v, _ = frame_gradient(model, solver, state, ctl, loss, k, prev_v, prev_acc)
        model.set_spring_log_y(model.log_y_np - 1e-3 * np.sign(g))  # the Adam step's cost is negligible
        state = model.state()
        state.x.assign(x)
        state.v.assign(v)
        wp.synchronize_device(device)
        if k > 2:
            times.append(time.perf_counter() - t0)
        v = v.astype(np.float64)
        prev_acc, prev_v = v - prev_v, v
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="all")
    ap.add_argument("--budget", type=int, default=150, help="stage-1 evaluations")
    ap.add_argument("--epochs", type=int, default=15, help="stage-2 epochs")
    args = ap.parse_args()
    wp.config.log_level = wp.LOG_WARNING  # no init banner (warp 1.19 has no config.quiet)
    wp.init()
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    if args.device != "all":
        devices = [args.device]
    data, truth = synthetic_case("rope", seed=0)
    print(f"sysid_rope_particles {data.num_particles} count")
    print(f"sysid_rope_train_frames {len(data.train_frames)} count")
    for dev in devices:
        tag = "cpu" if dev == "cpu" else "cuda"
        for substeps, frames in ((40, 10), (667, 3)):
            sec = _seconds_per_iteration(data, truth, substeps, dev, frames)
            print(f"sysid_rope_{tag}_stage2_s_per_iteration_{substeps}_substeps {sec:.4f} s")
        base = SimParams(dt=1.0 / 1200, substeps=40)
        loss = SequenceLoss(data)
        evaluate(build_model(data, truth["params"], base, dev), data, loss)  # warm-up
        t0 = time.perf_counter()
        for _ in range(5):
            evaluate(build_model(data, truth["params"], base, dev), data, loss,
                     frames=len(data.train_frames), acc=False)
        print(f"sysid_rope_{tag}_stage1_s_per_evaluation_40_substeps {(time.perf_counter() - t0) / 5:.4f} s")

    cfg = FitConfig(dt=1.0 / 1200, substeps=40, progress=False,
                    initial=GlobalParams(spring_Y=1000.0, control_radius=0.02, control_max_neighbors=8),
                    cma=CMAConfig(budget=args.budget, search=SEARCH, ranges=("spring_Y=100:10000",)),
                    adam=AdamConfig(epochs=args.epochs, lr=0.02, y_min=50.0, y_max=1e4))
    t0 = time.perf_counter()
    res = identify(data, cfg, log=lambda _msg: None)
    total = time.perf_counter() - t0
    n = res.model.num_object_springs
    print(f"sysid_rope_cpu_identify_total {total:.1f} s")
    print(f"sysid_rope_val_error_initial {1e3 * res.evals['initial'].val_error:.2f} mm")
    print(f"sysid_rope_val_error_stage1 {1e3 * res.evals['stage1'].val_error:.2f} mm")
    print(f"sysid_rope_val_error_final {1e3 * res.evals['final'].val_error:.2f} mm")
    print(f"sysid_rope_spring_Y_spearman {spearmanr(res.log_y[:n], truth['log_y'][:n]).statistic:.3f} ratio")


if __name__ == "__main__":
    main()

"""PhysTwin cases: the restricted loader refuses executable pickles, a case written here imports and
simulates the frames its arrays describe, export round-trips, and PhysTwin's self-collision rule."""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
import zipfile

import numpy as np
import pytest

from twinbench.construct.phystwin import (
    FLIP_Z,
    PhysTwinFormatError,
    controller_springs,
    import_case,
    load_pickle,
    load_torch_zip,
    phystwin_config,
    phystwin_springs,
    read_case,
    save_torch_zip,
    write_case,
)
from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.physics.model import lattice

# ------------------------------------------------------------------------------ restricted loading


class _Evil:
    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


def test_malicious_pickle_is_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "pwned"
    bad = tmp_path / "final_data.pkl"
    bad.write_bytes(pickle.dumps({"object_points": np.zeros((1, 2, 3)), "x": _Evil(marker)}))
    with pytest.raises(PhysTwinFormatError, match=r"refuses to load the pickled object (posix|os)\.system"):
        load_pickle(bad)
    assert not marker.exists()
    # the same inside a torch archive
    buf = io.BytesIO()
    pickle.dump({"spring_Y": _Evil(marker)}, buf, protocol=2)
    with zipfile.ZipFile(tmp_path / "best_1.pth", "w") as zf:
        zf.writestr("best_1/data.pkl", buf.getvalue())
    with pytest.raises(PhysTwinFormatError, match="refuses to load"):
        load_torch_zip(tmp_path / "best_1.pth")
    assert not marker.exists()


def test_plain_pickles_of_arrays_and_numpy_scalars_load(tmp_path):
    obj = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.float64(0.25), "c": [1, "x", None],
           "d": (True, 2.5), "e": np.zeros((0, 3)), "f": np.ones((3, 2))[:, 0]}
    for proto in (2, 4, 5):
        p = tmp_path / f"p{proto}.pkl"
        p.write_bytes(pickle.dumps(obj, protocol=proto))
        out = load_pickle(p)
        assert out["b"] == 0.25 and out["c"] == [1, "x", None] and out["d"] == (True, 2.5)
        np.testing.assert_array_equal(out["a"], obj["a"])
        assert out["e"].shape == (0, 3)
    objarr = tmp_path / "obj.pkl"
    objarr.write_bytes(pickle.dumps({"a": np.array([{"k": 1}], dtype=object)}))
    with pytest.raises(PhysTwinFormatError):
        load_pickle(objarr)


def test_torch_zip_round_trip_and_strided_views(tmp_path):
    data = {"spring_Y": np.linspace(1, 2, 7, dtype=np.float32), "collide_elas": np.array([0.5], np.float32),
            "num_object_springs": 5, "epoch": 3, "m": np.arange(12, dtype=np.int64).reshape(3, 4),
            "flag": np.array([True, False]), "nested": {"lr": 1e-3, "betas": (0.9, 0.99)}}
    save_torch_zip(data, tmp_path / "best_3.pth")
    out = load_torch_zip(tmp_path / "best_3.pth")
    for k in ("spring_Y", "collide_elas", "m", "flag"):
        np.testing.assert_array_equal(out[k], data[k])
        assert out[k].dtype == data[k].dtype
    assert out["nested"] == {"lr": 1e-3, "betas": (0.9, 0.99)} and out["epoch"] == 3
    torch = pytest.importorskip("torch", reason="torch (extra `torch`) checks the archive layout both ways")
    t = torch.load(tmp_path / "best_3.pth", weights_only=True)
    assert torch.equal(t["m"], torch.arange(12).reshape(3, 4))
    torch.save({"x": torch.arange(10.0)[::2], "y": torch.ones(2, 3).t()}, tmp_path / "t.pth")
    back = load_torch_zip(tmp_path / "t.pth")
    np.testing.assert_array_equal(back["x"], np.arange(10.0)[::2])
    assert back["y"].shape == (3, 2)


def test_out_of_bounds_tensor_view_is_refused(tmp_path):
    save_torch_zip({"a": np.zeros(4, np.float32)}, tmp_path / "a.pth")
    with zipfile.ZipFile(tmp_path / "a.pth") as zf:
        files = {n: zf.read(n) for n in zf.namelist()}
    pkl = files["a/data.pkl"]
    files["a/data.pkl"] = pkl.replace(b"K\x04\x85", b"K\x40\x85")  # size (4,) -> (64,)
    with zipfile.ZipFile(tmp_path / "b.pth", "w") as zf:
        for n, b in files.items():
            zf.writestr(n, b)
    with pytest.raises(PhysTwinFormatError, match="reaches element"):
        load_torch_zip(tmp_path / "b.pth")


# ------------------------------------------------------------------------------ a whole case

PARAMS = {
    "global_spring_Y": 3e4, "object_radius": 0.02, "object_max_neighbours": 20, "controller_radius": 0.03,
    "controller_max_neighbours": 12, "collide_elas": 0.4, "collide_fric": 0.6, "collide_object_elas": 0.7,
    "collide_object_fric": 0.3, "collision_dist": 0.02, "drag_damping": 3.0, "dashpot_damping": 100.0,
}
FRAMES = 3


def _make_case(tmp_path, *, damping=(3.0, 100.0), written=None, n_frames=FRAMES):
    """A lifted soft bar simulated in the z-up frame with (drag, dashpot) = `damping`, written as a
    PhysTwin case in its reverse_z frame with `written` (default: the same) as its stage-1 damping.
    Returns (case folder, z-up frames (F+1, N, 3))."""
    rng = np.random.default_rng(0)
    pts = lattice(6, 3, 3, 0.01, origin=(0.0, 0.0, 0.0)).astype(np.float32)
    ctrl0 = np.array([[-0.005, 0.0, 0.0], [-0.005, 0.02, 0.02]])
    springs = phystwin_springs(pts, PARAMS["object_radius"], PARAMS["object_max_neighbours"])
    cs = controller_springs(pts, ctrl0, PARAMS["controller_radius"], PARAMS["controller_max_neighbours"])
    y = np.exp(rng.uniform(np.log(5e3), np.log(5e4), len(springs) + len(cs))).astype(np.float32)
    params = SimParams(drag_damping=damping[0], dashpot_damping=damping[1], ground_restitution=0.4,
                       ground_friction=0.6, object_restitution=0.7, object_friction=0.3, collision_dist=0.02)
    b = ModelBuilder(params)
    b.add_body(pts, springs=springs, spring_Y=y[: len(springs)])
    b.add_control_points(ctrl0, springs=cs, spring_Y=y[len(springs):])
    model = b.finalize("cpu")
    solver = SpringMassSolver(model)
    state, control = model.state(), model.control()
    frames = [pts.copy()]
    ctrl = [ctrl0]
    for k in range(1, n_frames + 1):
        nxt = ctrl0 + [0.0, 0.0, 0.01 * k]
        control.set_control_points(ctrl[-1], nxt)
        solver.simulate_frame(state, control)
        frames.append(state.x.numpy().copy())
        ctrl.append(nxt)
    frames = np.stack(frames)
    flip = FLIP_Z[:3, :3]
    n = len(pts)
    final = {
        "object_points": (frames @ flip.T).astype(np.float32),  # PhysTwin frame (reverse_z)
        "object_colors": np.full((n_frames + 1, n, 3), 0.5, np.float32),
        "object_visibilities": np.ones((n_frames + 1, n), bool),
        "object_motions_valid": np.ones((n_frames + 1, n), bool),
        "controller_points": (np.stack(ctrl) @ flip.T).astype(np.float32),
        "surface_points": np.zeros((0, 3)),
        "interior_points": np.zeros((0, 3)),
    }
    one = {"collide_elas": 0.4, "collide_fric": 0.6, "collide_object_elas": 0.7, "collide_object_fric": 0.3}
    ck = {"spring_Y": y, "num_object_springs": len(springs),
          **{k: np.array([v], np.float32) for k, v in one.items()}}
    drag, dashpot = written or damping
    op = {k: (np.float64(v) if not k.endswith("neighbours") else int(v)) for k, v in PARAMS.items()}
    op.update(drag_damping=np.float32(drag), dashpot_damping=np.float32(dashpot))  # CMA-ES writes float32
    write_case(tmp_path / "case", final, op, ck, epoch=7)
    return tmp_path / "case", frames


def _simulate_imported(imp, controller_frames_phystwin):
    """Simulate the imported object with the case's controller trajectory; z-up frames (F+1, N, 3)."""
    flip = imp.frame[:3, :3]
    fields = {k: v for k, v in imp.sim.items()}
    b = ModelBuilder(SimParams(**fields))
    b.add_body(imp.particles, springs=imp.springs, rest_lengths=imp.rest_lengths, spring_Y=imp.spring_Y)
    ctrl = controller_frames_phystwin.astype(np.float64) @ flip.T
    b.add_control_points(ctrl[0], springs=imp.controller_springs, spring_Y=imp.controller_spring_Y)
    model = b.finalize("cpu")
    solver = SpringMassSolver(model)
    state, control = model.state(), model.control()
    out = [state.x.numpy().copy()]
    for k in range(1, len(ctrl)):
        control.set_control_points(ctrl[k - 1], ctrl[k])
        solver.simulate_frame(state, control)
        out.append(state.x.numpy().copy())
    return np.stack(out)


def test_case_imports_and_simulates_the_frames_it_describes(tmp_path):
    folder, frames = _make_case(tmp_path)
    case = read_case(folder)
    assert case.sources["checkpoint"].endswith("best_7.pth")
    imp = import_case(case, reverse_z=True)
    np.testing.assert_allclose(imp.particles, frames[0], atol=1e-7)
    assert imp.sim["ground_restitution"] == pytest.approx(0.4) and imp.sim["collision_exclusion"] == "none"
    sim = _simulate_imported(imp, case.final_data["controller_points"])
    flip = FLIP_Z[:3, :3]
    described = case.final_data["object_points"].astype(np.float64) @ flip.T  # back to z up
    np.testing.assert_allclose(sim, described, atol=2e-6)
    assert np.abs(described[-1] - described[0]).max() > 0.02  # the bar really moved


def test_fractional_damping_runs_as_phystwins_loader_truncates_it(tmp_path):
    """PhysTwin's config casts trained drag / dashpot to its int defaults: 2.6 -> 2, 75.5 -> 75."""
    folder, frames = _make_case(tmp_path, damping=(2.0, 75.0), written=(2.6, 75.5), n_frames=12)
    case = read_case(folder)
    cfg = phystwin_config(case.optimal_params)
    assert (cfg["drag_damping"], cfg["dashpot_damping"]) == (2, 75) and type(cfg["drag_damping"]) is int
    assert cfg["collision_dist"] == pytest.approx(0.02) and cfg["object_max_neighbours"] == 20
    assert float(case.optimal_params["drag_damping"]) == pytest.approx(2.6)  # the file keeps its value
    imp = import_case(case)
    assert (imp.sim["drag_damping"], imp.sim["dashpot_damping"]) == (2.0, 75.0)
    ctrl = case.final_data["controller_points"]
    sim = _simulate_imported(imp, ctrl)
    assert np.abs(sim - frames).max() < 10e-6  # within 10 um of PhysTwin's rule
    frac = dict(imp.sim, drag_damping=2.6, dashpot_damping=75.5)
    kept = _simulate_imported(dataclasses.replace(imp, sim=frac), ctrl)
    assert np.abs(kept - frames).max() > 20e-6  # keeping the fractions would drift


def test_mismatched_checkpoint_is_refused(tmp_path):
    folder, _ = _make_case(tmp_path)
    case = read_case(folder)
    case.optimal_params["object_max_neighbours"] = 10  # springs rebuilt differently
    with pytest.raises(PhysTwinFormatError, match="do not match the checkpoint"):
        import_case(case)


def test_missing_files_and_fields_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="best_EPOCH.pth"):
        read_case(tmp_path)
    folder, _ = _make_case(tmp_path)
    p = folder / "optimal_params.pkl"
    p.write_bytes(pickle.dumps({"object_radius": 0.02}))
    with pytest.raises(PhysTwinFormatError, match=r"optimal_params.pkl: missing field\(s\)"):
        read_case(folder)


# ------------------------------------------------------------------------------ collision rule


def _two_particles(exclusion: str) -> np.ndarray:
    """Two particles 1 cm apart joined by a (soft) spring shorter than collision_dist = 2 cm, approaching
    at 2 m/s; returns their x velocities after one substep."""
    params = SimParams(dt=5e-5, substeps=1, gravity=(0.0, 0.0, 0.0), ground=False, drag_damping=0.0,
                       dashpot_damping=0.0, self_collision=True, object_restitution=1.0, object_friction=0.0,
                       collision_dist=0.02, collision_exclusion=exclusion)
    b = ModelBuilder(params)
    b.add_body([[0.0, 0.0, 0.5], [0.01, 0.0, 0.5]], springs=[[0, 1]], spring_Y=1.0,
               velocities=[[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    model = b.finalize("cpu")
    state, control = model.state(), model.control()
    SpringMassSolver(model).simulate_frame(state, control)
    return state.v.numpy()[:, 0]


def test_phystwin_collision_rule_collides_spring_connected_pairs():
    v_tb = _two_particles("springs")  # twinbench: the spring pair never collides
    v_pt = _two_particles("none")  # PhysTwin: it does (elastic: the velocities swap)
    assert v_tb[0] > 0.99 and v_tb[1] < -0.99
    np.testing.assert_allclose(v_pt, [-1.0, 1.0], atol=1e-2)
    with pytest.raises(ValueError, match="collision_exclusion"):
        SimParams(collision_exclusion="all")


def test_import_export_commands_round_trip_a_case(tmp_path):
    from twinbench.cli import main as cli
    from twinbench.twin import load_object

    folder, frames = _make_case(tmp_path)
    assert cli(["import-phystwin", str(folder), "--out", str(tmp_path / "obj"), "--name", "bar"]) == 0
    obj, sim = load_object(tmp_path / "obj")
    assert obj.name == "bar" and sim["collision_exclusion"] == "none"
    np.testing.assert_allclose(obj.particles, frames[0], atol=1e-7)
    original = read_case(folder)
    assert len(obj.spring_Y) == original.num_object_springs
    assert cli(["export-phystwin", str(tmp_path / "obj"), "--out", str(tmp_path / "back")]) == 0
    again = read_case(tmp_path / "back")
    for k, v in original.final_data.items():
        np.testing.assert_array_equal(again.final_data[k], v)
    np.testing.assert_array_equal(again.checkpoint["spring_Y"], original.checkpoint["spring_Y"])
    assert again.optimal_params == pytest.approx(original.optimal_params)
    assert again.scalar("collide_fric") == pytest.approx(original.scalar("collide_fric"))
    assert again.sources["checkpoint"].endswith("best_7.pth")


def test_final_data_becomes_sysid_input_in_the_z_up_frame(tmp_path):
    """A case's training data read as system-identification input: particles, observed and tracked
    points and controls in twinbench's z-up frame, the last fifth held out; `sysid` reads the folder."""
    from twinbench.construct.phystwin import sysid_data_from_final_data
    from twinbench.construct.sysid_io import load_input

    case, frames = _make_case(tmp_path)
    data = sysid_data_from_final_data(case / "final_data.pkl")
    np.testing.assert_allclose(data.particles, frames[0], atol=1e-6)
    np.testing.assert_allclose(data.observed, frames, atol=1e-6)
    np.testing.assert_allclose(data.tracked, frames, atol=1e-6)
    np.testing.assert_array_equal(data.tracked_indices, np.arange(frames.shape[1]))
    assert data.controls[:, :, 2].max() > data.controls[0, :, 2].max()  # lifted: z grows upwards
    assert data.validation_frames == max(1, (FRAMES + 1) // 5)
    np.testing.assert_array_equal(load_input(case).observed, data.observed)  # the folder works too

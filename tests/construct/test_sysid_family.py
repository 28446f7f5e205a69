"""The held-out sysid family: seeded, varied (layouts, interactions, stiffness patterns, contact), noisy
and partly visible; the fit with default options handles a few of its cases without diverging."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from twinbench.construct.sysid_family import (
    INTERACTIONS,
    LAYOUTS,
    contact_effect,
    family_case,
    step_effect,
)
from twinbench.physics import SimParams
from twinbench.physics.sysid import (
    AdamConfig,
    CMAConfig,
    FitConfig,
    GlobalParams,
    SequenceLoss,
    build_model,
    evaluate,
    identify,
    spring_regions,
    stable_substeps,
    stage1_loss,
    stage4_cma,
)


@pytest.fixture(scope="module")
def family():
    return [family_case(i) for i in range(12)]


def test_family_is_seeded_and_varied(family):
    assert {t["layout"] for _, t in family} == set(LAYOUTS)
    assert {t["interaction"] for _, t in family} == set(INTERACTIONS)
    assert {(t["layout"], t["interaction"]) for _, t in family}.__len__() == 12
    assert {t["pattern"] for _, t in family} == {"regions2", "regions3", "gradient"}
    assert any(t["slides"] for _, t in family) and any(t["impacts"] for _, t in family)
    assert len({round(t["params"].ground_friction, 6) for _, t in family}) == 12
    assert len({round(t["params"].spring_radius, 6) for _, t in family}) == 12
    for data, t in family:
        n = data.springs.shape[0]
        y = np.exp(t["log_y"][:n].astype(np.float64))
        assert y.max() / y.min() > 4.0  # a stiffness pattern, not one value
        assert data.num_frames == 30 and data.validation_frames == 6
        assert 0.7 < data.visibility.mean() < 0.9
        noise = data.tracked - t["positions"][:, data.tracked_indices]
        assert 0.8e-3 < noise.std() < 1.2e-3
        assert np.abs(t["positions"][-1] - t["positions"][0]).max() > 0.02  # it really moves
    again, t_again = family_case(5)
    np.testing.assert_array_equal(again.observed, family[5][0].observed)
    other, _ = family_case(5, seed=1)
    assert other.observed.shape != again.observed.shape or not np.allclose(other.observed, again.observed)


def test_contact_effect_says_which_motions_show_friction_and_restitution(family):
    """A drag moves with the ground's friction and hardly with its restitution; a drop of a sheet the other
    way round (it falls straight: friction has nothing to act on); a smaller change moves it less."""
    drag, drop = family[4], family[5]  # rope drag, cloth drop
    assert (drag[1]["interaction"], drop[1]["interaction"]) == ("drag", "drop")
    on_drag, on_drop = contact_effect(*drag), contact_effect(*drop)
    assert on_drag["friction"] > 1e-3 and on_drag["restitution"] < 0.1e-3
    assert on_drop["friction"] < 1e-5 and on_drop["restitution"] > 0.1e-3
    assert contact_effect(*drag, delta=0.03)["friction"] < 0.5 * on_drag["friction"]


def test_step_effect_tells_a_converged_motion_from_a_chaotic_one(family):
    """The truth's own values at 1.5x / 2x its substeps: a rope drag tracks at the noise floor whatever the
    step (it converged); seed 3's irregular lift (measured: 2.9x and 6.9x the floor) depends on the step,
    and at the truth's own step the error is the floor itself."""
    def floor(data, t):
        xt = t["positions"][:, data.tracked_indices]
        return np.mean([np.mean(np.linalg.norm(xt[k][m] - data.tracked[k][m], axis=1))
                        for k in data.val_frames for m in [data.motion_valid[k]]])

    drag = family[4]
    assert step_effect(*drag) < 1.2 * floor(*drag)
    chaotic = family_case(7, seed=3)
    assert step_effect(*chaotic) > 2.0 * floor(*chaotic)
    assert step_effect(*chaotic, factors=(1.0,)) == pytest.approx(floor(*chaotic), rel=0.02)


def test_track_noise_is_not_taken_from_a_ringing_object(family):
    """The family's tracks carry 1 mm of noise per axis. The lifted irregular blob and block ring faster
    than the frame rate resolves, so a track's own second differences read 1.5-1.6x that (which kept the
    second start from running where it was needed); the offsets from the nearest neighbour do not ring."""
    from twinbench.physics.sysid_guess import _tracks, difference_noise, track_noise

    for data, _ in [family[7], family[10], family_case(7, seed=1)]:
        assert difference_noise(_tracks(data)[0], 2) > 1.4e-3, data.name
        assert track_noise(data) == pytest.approx(1e-3, rel=0.1), data.name
    for data, _ in family[:4]:
        assert track_noise(data) == pytest.approx(1e-3, rel=0.12), data.name


def test_stage4_moves_a_stiffness_region_and_the_damping_together():
    """Stage 4 on a noise-free cloth drag, from the truth with one of four stiffness regions twice too stiff
    and the dashpot 2.5x too high (stiffness alone or damping alone can partly stand in for the other): the
    loss falls over 5x and both move back towards the truth; the other regions stay near theirs."""
    data, t = family_case(1, noise=1e-5)
    tp, n = t["params"], len(t["springs"])
    model = build_model(data, tp, SimParams())
    region = spring_regions(model, 4)[:n]
    ly = t["log_y"].astype(np.float64)
    start_y = ly[:n].copy()
    start_y[region == 0] += math.log(2.0)
    start = replace(tp, dashpot_damping=2.5 * tp.dashpot_damping)

    def base_of(p, y_top):
        sub = stable_substeps(model, y_top, max(p.dashpot_damping, 100.0), 30.0)
        return FitConfig().base_params(30.0, sub)

    p4, (y4, c4), history = stage4_cma(data, start, (start_y, float(ly[n:].mean())), region,
                                      ("drag_damping", "dashpot_damping"), CMAConfig(), 120, base_of,
                                      log=lambda _m: None)
    assert len(history) == 120 and history[-1]["best"] < 0.2 * history[0]["loss"]
    again = stage1_loss(data, p4, base_of(p4, float(np.exp(max(y4.max(), c4)))), SequenceLoss(data),
                        hold=(y4, c4))
    assert history[-1]["best"] == pytest.approx(again)  # what it returns is what it scored
    dash = tp.dashpot_damping
    assert abs(p4.dashpot_damping - dash) < 0.5 * abs(start.dashpot_damping - dash)
    shift = [float(np.mean(y4[region == r] - ly[:n][region == r])) for r in range(4)]
    assert abs(shift[0]) < 0.7 * math.log(2.0) and max(abs(v) for v in shift[1:]) < 0.35
    assert np.all(np.abs(y4 - start_y)[region == 0] <= math.log(3.0) + 1e-9)  # within STAGE4_SPAN


def test_stable_substeps_scale_with_stiffness_and_keep_the_truth_finite():
    data, truth = family_case(2)  # a block dropped on the ground
    topo = build_model(data, GlobalParams(), SimParams())
    s1, s100 = (stable_substeps(topo, y, 0.0, 30.0) for y in (1e3, 1e5))
    assert 8 <= s100 / s1 <= 11  # omega ~ sqrt(Y)
    assert stable_substeps(topo, 1e3, 200.0, 30.0) > s1  # the dashpot needs a smaller step too
    y_max = float(np.exp(truth["log_y"].max()))
    n = stable_substeps(topo, y_max, truth["params"].dashpot_damping, 30.0)
    model = build_model(data, truth["params"], SimParams(dt=1.0 / (30 * n), substeps=n),
                        log_y=truth["log_y"])
    from twinbench.physics.sysid import rollout

    xs, _ = rollout(model, data.controls, data.num_frames - 1)
    assert np.all(np.isfinite(xs)) and np.abs(xs - truth["positions"]).max() < 5e-3


@pytest.mark.parametrize("i", [1, pytest.param(2, marks=pytest.mark.slow)])  # case 2 (a drop): slow
def test_default_fit_on_family_cases_improves_and_reports(i):
    """Default options (automatic substeps, stiffness scan, regions), small budgets: no divergence, the
    fit beats its start, and the result says what the motion constrains."""
    data, truth = family_case(i, frames=14, validation_frames=3)
    cfg = FitConfig(progress=False, cma=CMAConfig(budget=30), adam=AdamConfig(epochs=2))
    res = identify(data, cfg, log=lambda _m: None)
    assert not any(e.diverged for e in res.evals.values())
    val = list(data.val_frames)
    floor = np.mean([np.linalg.norm(truth["positions"][k][m] - data.tracked[k][m], axis=1).mean()
                     for k in val for m in [data.motion_valid[k]]])  # what the truth scores
    # halves the start's error, or is within twice the noise floor (a drop is at rest by then)
    assert res.evals["final"].val_error < max(0.5 * res.evals["initial"].val_error, 2.0 * floor)
    fitted = {k: e.terms["chamfer"] + e.terms["track"] for k, e in res.evals.items()}  # stage 1's objective
    assert fitted["final"] < fitted["initial"]
    # by default every training frame is fitted and the last stage is kept (--select-frames chooses)
    assert res.selection["kept"] == "stage3" and res.evals["final"] is res.evals["stage3"]
    # stage 3 searched the global parameters other than the spring rule with stage 2's stiffness held
    assert res.stage3_history and "spring_Y" not in res.stage3_history[0]["params"]
    assert fitted["stage3"] <= fitted["stage2"] * 1.001  # by its objective (no acceleration term)
    assert res.selection["frames"] == [] and "last stage" in res.selection["rule"]
    assert set(res.identifiability) >= {"spring_Y", "ground_friction", "dashpot_damping"}
    sy = res.identifiability["spring_Y"]
    assert sy["low"] <= sy["best"] <= sy["high"] and sy["samples"] >= 1
    assert math.isfinite(res.params.spring_Y) and isinstance(res.notes, list)
    # and which stiffness regions the motion constrains: one row per fitted region (control springs last)
    rows = res.region_identifiability["regions"]
    assert len(rows) == res.regions.max() + 1 and sum(r["springs"] for r in rows) == res.model.num_springs
    assert all(r["std"] > 0 and r["constrained"] == (r["std"] < res.region_identifiability["std_limit"])
               for r in rows)


def test_a_second_round_starts_where_the_first_ended():
    """``rounds=2``: stages 2 and 3 run again, the second stage 2 from the first stage 3's end point (its
    contact values and held stiffness), the first round's stages kept under their round's name."""
    data, _ = family_case(1, frames=14, validation_frames=3)
    cfg = FitConfig(progress=False, rounds=2, cma=CMAConfig(budget=30), adam=AdamConfig(epochs=2),
                    stage3_budget=30)
    res = identify(data, cfg, log=lambda _m: None)
    assert [k for k in res.evals if "stage" in k] == ["stage1", "stage2_round1", "stage3_round1", "stage2",
                                                       "stage3"]
    assert res.selection["kept"] == "stage3" and res.evals["final"] is res.evals["stage3"]
    end3 = min((r for r in res.stage3_history if r["round"] == 1), key=lambda r: r["loss"])["params"]
    start2 = next(r for r in res.stage2_history if r["round"] == 2)
    assert {"ground_friction", "ground_restitution"} <= set(start2)
    assert all(start2[k] == pytest.approx(end3[k], abs=1e-3)
               for k in ("ground_friction", "ground_restitution"))
    # the round starts at the first round's stage 3 model: same tracks (stage 2's loss weighs differently)
    assert start2["train_error"] == pytest.approx(res.evals["stage3_round1"].train_error, rel=0.05)
    # the histories number on across the rounds
    assert [r["epoch"] for r in res.stage2_history] == list(range(len(res.stage2_history)))
    assert [r["evaluation"] for r in res.stage3_history] == list(range(len(res.stage3_history)))


def _bench():
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).parents[2] / "benchmarks" / "sysid.py"
    spec = importlib.util.spec_from_file_location("bench_sysid", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def test_withheld_springs_rank_against_the_true_springs_nearest_each_fit_region():
    """With the springs withheld the fit's own springs (another radius rule) differ from the truth's: each
    fit region is compared with the true springs whose midpoints lie nearest its springs. A rope soft on
    its left half and stiff on its right, fitted springs in two regions by halves: the truth's two values
    come back per region, in the fit's region order (within a few springs at the boundary, whose nearest
    fit spring is a tie)."""
    from types import SimpleNamespace

    from twinbench.physics.model import lattice, radius_springs

    pts = lattice(12, 2, 1, 0.01)
    true_sp = radius_springs(pts, 0.021, 30)  # with the diagonals and the 2 cm springs
    fit_sp = radius_springs(pts, 0.0105, 30)  # the ladder alone
    assert len(true_sp) > len(fit_sp)
    true_mid = 0.5 * (pts[true_sp[:, 0], 0] + pts[true_sp[:, 1], 0])
    log_y = np.where(true_mid < 0.055, math.log(300.0), math.log(3000.0))
    fit_mid = 0.5 * (pts[fit_sp[:, 0], 0] + pts[fit_sp[:, 1], 0])
    region = np.where(fit_mid < 0.055, 1, 0)  # k-means labels need not follow x
    res = SimpleNamespace(model=SimpleNamespace(num_object_springs=len(fit_sp), springs_np=fit_sp, x0_np=pts))
    truth = {"springs": true_sp, "log_y": np.concatenate([log_y, [0.0, 0.0]])}  # 2 control springs after
    bench = _bench()
    got = bench._truth_by_fit_region(res, truth, pts, region)
    assert got == pytest.approx([math.log(3000.0), math.log(300.0)], abs=0.15)
    assert bench._rank([1.0, 2.0, 3.0], [0.5, math.nan, 0.7]) == pytest.approx(1.0)  # NaN truth left out


@pytest.mark.slow
@pytest.mark.timeout(1800)  # 12 fits one after another: about 9 minutes alone on 2 cores, more on busy ones
def test_family_with_default_options():
    """The benchmark's family (12 cases, default options): no divergence, validation error within 2x the
    noise floor for the median case (the figures are printed by benchmarks/sysid.py)."""
    bench = _bench()
    rows = [bench.run_case(i, 0) for i in range(12)]
    assert all("error" not in r and not r["diverged"] for r in rows)
    assert np.median([r["val_final"] / r["floor"] for r in rows]) <= 2.0
    # each row holds the fit itself: rebuilt from the (JSON) row, it scores the fit's validation error again
    row = json.loads(json.dumps(rows[7]))
    data, _ = family_case(7, 0)
    model = build_model(data, GlobalParams(**row["fit_params"]), SimParams(**row["fit_sim"]),
                        log_y=np.array(row["fit_log_y"], np.float32))
    assert evaluate(model, data, SequenceLoss(data)).val_error == pytest.approx(row["val_final"], rel=1e-5)


@pytest.mark.slow
def test_the_attachment_families_find_the_hand_of_the_irregular_lift():
    """Family seed 1's irregular lift (the hand holds the 11 particles within 1.5 cm of its two points,
    at most 6 each), one start (~1 minute): stage 1's search ends attached elsewhere (training frames 6.4
    mm); scored among the attachment families at its end, the hand becomes the truth's and one particle
    more, and the fit tracks its training frames at 3.5 mm (before the families: 6.6x the noise floor after
    a second start that scored a grid of nine attachments, 17x without it). Measured: validation 3.5x the
    floor; 2.4x with exactly the truth's hand before the tracks' noise was read from neighbours' offsets
    (the stiffness guess 4 % other led stage 1 elsewhere). With the default two starts, the first run's
    training error (2.2x the tracks' noise floor) starts a second, which trains 6 % lower and validates at
    3.0x (BENCHMARKS.md)."""
    data, truth = family_case(7, 1)
    res = identify(data, FitConfig(progress=False, attachment_starts=False), log=lambda _m: None)

    def held(model) -> set:  # (control point, particle) pairs
        return {tuple(s) for s in model.springs_np[model.num_object_springs:].tolist()}

    hand = held(build_model(data, truth["params"], SimParams()))
    assert len(hand) == 11 and hand <= held(res.model) and len(held(res.model)) <= 12
    assert "second_start" not in res.selection
    assert res.evals["stage1"].train_error > 1.5 * res.evals["final"].train_error
    val = list(data.val_frames)
    floor = np.mean([np.linalg.norm(truth["positions"][k][m] - data.tracked[k][m], axis=1).mean()
                     for k in val for m in [data.motion_valid[k]]])
    assert res.evals["final"].val_error < 4.0 * floor


def test_a_drop_keeps_the_restitution_measured_from_its_bounce():
    """The family's rope drop (default options): the motion barely constrains ground restitution (stage
    1's near-best candidates span most of [0, 1]), so the value measured from the bounce replaces the
    search's arbitrary point, at little cost in training loss; with --keep-guess 0 the search's stays."""
    from dataclasses import replace

    data, truth = family_case(8)
    res = identify(data, FitConfig(progress=False, stage2=False), log=lambda _m: None)
    guess = res.guesses["ground_restitution"]
    ident = res.identifiability["ground_restitution"]
    assert guess["used"] and not ident["constrained"] and ident["guess_kept"]
    assert res.params.ground_restitution == pytest.approx(guess["value"])
    trial = res.stage1_history[-1]
    assert trial["guess_kept"] and trial["loss"] <= 1.1 * min(r["loss"] for r in res.stage1_history[:-1])
    assert any("ground_restitution" in n and "kept instead" in n for n in res.notes)
    assert abs(res.params.ground_restitution - truth["params"].ground_restitution) < 0.15

    off = identify(data, FitConfig(progress=False, stage2=False, keep_guess=0.0), log=lambda _m: None)
    assert off.params.ground_restitution == pytest.approx(ident["best"])
    assert not any("guess_kept" in r for r in off.stage1_history)
    assert [n for n in off.notes if "end of its search range" not in n] == []  # (a soft spring_Y: at 13)
    assert replace(off.params, ground_restitution=res.params.ground_restitution) == res.params

"""A PhysTwin-like rope kept in tests/data/sysid_rope (made by its make.py with twinbench's simulator and
PhysTwin's conventions: unit masses, springs by the 2 cm radius rule, three stiffness regions 8k / 60k /
25k, ground restitution 0.3 and friction 0.7, drag 2, dashpot 60; hand points lift, drag and lower it; 1 mm
noise, 85 % visible, the last 9 of 45 frames held out): motion the fit's defaults were not made on."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from twinbench.construct.sysid_io import load_sysid_data
from twinbench.physics import SimParams
from twinbench.physics.sysid import FitConfig, GlobalParams, build_model, fit_view, identify, selection_count
from twinbench.physics.sysid_guess import physical_guesses

CASE = Path(__file__).parents[1] / "data" / "sysid_rope"


@pytest.fixture(scope="module")
def rope():
    return load_sysid_data(CASE), dict(np.load(CASE / "truth.npz"))


def test_case_is_what_its_generator_makes(rope):
    from twinbench.construct.sysid_synthetic import PHYSTWIN_ROPE_Y

    data, truth = rope
    assert (data.num_frames, data.validation_frames, data.num_particles, data.num_controls) == (45, 9, 40, 3)
    n = truth["springs"].shape[0]
    np.testing.assert_allclose(np.exp(truth["log_y"][:n].astype(np.float64)),
                               np.asarray(PHYSTWIN_ROPE_Y)[truth["region"]], rtol=1e-5)
    assert 0.8 < data.visibility.mean() < 0.9
    noise = data.tracked - truth["positions"][:, data.tracked_indices]
    assert 0.8e-3 < noise.std() < 1.2e-3
    z = truth["positions"][:, :, 2]
    assert z.max() > 0.08 and z[-1].max() < 0.03  # lifted, then lowered back


def test_guesses_scale_the_stiffness_and_bound_the_friction(rope):
    """The data-based starting values: stiffness within a decade of the truth's geometric mean (the
    control springs' load over their strain), friction a lower bound of the truth's 0.7, no bounce to
    measure restitution from."""
    data, truth = rope
    fit = fit_view(data, selection_count(data, 0.2))
    g = physical_guesses(fit, build_model(fit, GlobalParams(), SimParams()), GlobalParams().control_radius)
    n = truth["springs"].shape[0]
    y_true = math.exp(float(np.mean(truth["log_y"][:n])))
    assert y_true / 10 < g["spring_Y"]["value"] < 10 * y_true, (g["spring_Y"], y_true)
    assert 0.05 < g["ground_friction"]["value"] <= float(truth["ground_friction"])
    assert g["ground_friction"]["lower_bound"] and g["ground_restitution"]["value"] is None


@pytest.mark.slow
def test_default_fit_lowers_validation_error_and_separates_the_stiff_region(rope):
    data, truth = rope
    res = identify(data, FitConfig(progress=False), log=lambda _m: None)
    assert not any(e.diverged for e in res.evals.values())
    assert res.evals["final"].val_error < 0.5 * res.evals["initial"].val_error
    if res.selection["kept"] == "stage2":  # per-region stiffness: the 60k region is the stiffest
        n = res.model.num_object_springs
        ly, region = res.log_y[:n].astype(np.float64), truth["region"]
        med = [float(np.median(ly[region == r])) for r in range(3)]
        assert med[1] > max(med[0], med[2]), np.exp(med)

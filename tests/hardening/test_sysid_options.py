"""`twinbench sysid` under bad options and degenerate or damaged input (issue 25): options out of range,
an object whose particles give no springs, and corrupted arrays are one line naming the option or file,
exit code 2, before any simulation runs and with nothing written."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinbench.cli import main as cli
from twinbench.construct.sysid_io import save_sysid_data


@pytest.fixture()
def case_dir(tmp_path, sysid_small):
    save_sysid_data(sysid_small, tmp_path / "case")
    return tmp_path / "case"


def _run(args, out, capsys) -> list[str]:
    assert cli(["sysid", *args, "--out-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert not out.exists()
    return err


@pytest.mark.parametrize(("args", "needle"), [
    (["--cma.popsize", "1000000000"], "--cma.popsize: expected an integer in [0, 1000]"),
    (["--cma.budget", "0"], "--cma.budget: expected an integer in [1, 100000]"),
    (["--dt", "-1"], "--dt: expected a number in [0.0, 0.1]"),
    (["--dt", "nan"], "--dt: expected a number in [0.0, 0.1]"),
    (["--substeps", "-3"], "--substeps: expected an integer in [0, 100000]"),
    (["--adam.lr", "inf"], "--adam.lr: expected a number in [0.0, 10.0]"),
    (["--adam.y-min", "0"], "--adam.y-min: expected a number in (0.0, 1000000000000.0]"),
    (["--adam.contact-after", "2"], "--adam.contact-after: expected a number in [0.0, 1.0]"),
    (["--initial.spring-radius", "0"], "--initial.spring-radius: expected a number in (0.0, 10.0]"),
    (["--initial.ground-friction", "nan"], "--initial.ground-friction: expected a number in [0.0, 2.0]"),
    (["--weights.acc", "-1"], "--weights.acc: expected a number in [0.0, 1000000.0]"),
])
def test_options_out_of_range_are_one_line(case_dir, tmp_path, capsys, args, needle):
    err = _run(["--data", str(case_dir), *args], tmp_path / "out", capsys)
    assert len(err) == 1 and needle in err[0], err


def test_particles_at_one_point_give_no_object(tmp_path, sysid_small, capsys):
    """Every particle at one point: no springs could join them; refused instead of writing a 0-spring
    object."""
    one = np.zeros_like(sysid_small.particles) + 0.1
    save_sysid_data(dataclasses.replace(sysid_small, particles=one), tmp_path / "case")
    case = tmp_path / "case"
    err = _run(["--data", str(case)], tmp_path / "out", capsys)
    assert len(err) == 1 and "no springs" in err[0] and "--initial.spring-radius" in err[0], err


def test_corrupted_arrays_name_the_file(case_dir, tmp_path, capsys):
    npz = case_dir / "data.npz"
    raw = bytearray(npz.read_bytes())
    raw[len(raw) // 2: len(raw) // 2 + 64] = b"\xff" * 64
    npz.write_bytes(bytes(raw))
    err = _run(["--data", str(case_dir)], tmp_path / "out", capsys)
    assert len(err) == 1 and "data.npz" in err[0], err


def test_dt_zero_is_automatic_and_a_tiny_dt_is_refused(case_dir, tmp_path, capsys):
    """--dt 0 (was an internal ZeroDivisionError) means automatic substeps, alone or with --substeps; a dt
    so small that it needs millions of substeps per frame (runs for hours) is refused before simulating."""
    from twinbench.physics.sysid import FitConfig

    auto, given = FitConfig(dt=0.0).base_params(30.0), FitConfig(dt=0.0, substeps=5).base_params(30.0)
    assert auto.substeps >= 1 and auto.dt * auto.substeps == pytest.approx(1 / 30)
    assert (given.substeps, given.dt) == (5, pytest.approx(1 / 150))
    for dt in ("1e-9", "5e-324"):
        err = _run(["--data", str(case_dir), "--dt", dt], tmp_path / "out", capsys)
        assert len(err) == 1 and f"--dt {float(dt)}: gives" in err[0] and "at most 100000" in err[0], err

"""HTML report: content computed from a synthetic store, notes for missing data, and a headless Chromium
check (no console errors, every image and video loads, screenshot)."""

from __future__ import annotations

import re
from pathlib import Path

import imageio.v2 as iio
import numpy as np
import pytest

from twinbench.cli import main as cli_main
from twinbench.evaluation import metrics
from twinbench.evaluation.report import VideoLimits, pair_replay, summarize, write_report
from twinbench.evaluation.report_browser import CHROMIUM, check_page
from twinbench.evaluation.store import EpisodeRecord, ResultsStore

# (policy, checkpoint, train_step) -> (sim successes of 16, real successes of 10)
TRUTH = {
    ("expert", "", None): (15, 9),
    ("act", "step_1000", 1000): (3, 1),
    ("act", "step_5000", 5000): (9, 5),
    ("act", "step_20000", 20000): (13, 6),
    ("diffusion", "step_10000", 10000): (6, 4),
    ("diffusion", "step_50000", 50000): (11, 8),
}
N_SIM, N_REAL = 16, 10
# replay of act@step_20000 on real init states 0..9: flip these init states' outcomes vs real
REPLAY_FLIPS = {2, 7}


def _frames(n=12, h=48, w=64):
    yy, xx = np.mgrid[0:h, 0:w]
    return [np.stack([(xx * 4 + 9 * i) % 256, (yy * 5) % 256, np.full_like(xx, 40 * (i % 6))], -1)
            .astype(np.uint8) for i in range(n)]


def build_store(tmp: Path) -> ResultsStore:
    """Synthetic run 'eval1' (sim + replay) and real run 'real' with known counts."""
    store = ResultsStore(tmp / "results.sqlite")
    mp4 = tmp / "rollout.mp4"
    iio.mimwrite(mp4, _frames(), fps=10)  # H.264 yuv420p via imageio-ffmpeg
    avi = tmp / "rollout.avi"
    iio.mimwrite(avi, _frames(), fps=10, codec="mpeg4")  # not playable in a browser: transcoded
    store.start_run("eval1", "push-t", {
        "task": "push-t", "initial_states": "push-t grid (16)", "episodes_per_policy": N_SIM, "seeds": [0],
        "versions": {"twinbench": "0.1.0", "warp-lang": "1.19.0"},
        "policies": ["expert", "act", "diffusion"]})
    recs = []
    for (policy, ckpt, step), (k_sim, k_real) in TRUTH.items():
        for i in range(N_SIM):
            video = None
            if policy == "act" and ckpt == "step_20000" and i < 2:
                video = str(mp4 if i == 0 else avi)
            recs.append(EpisodeRecord("eval1", "push-t", policy, ckpt, step, i, 0, "sim", i < k_sim, "ok",
                                      steps=1800, wall_time_s=3.5, video_path=video))
        for i in range(N_REAL):
            recs.append(EpisodeRecord("real", "push-t", policy, ckpt, step, i, 0, "real", i < k_real, "ok"))
    # errored episodes (not failures): 2 sim_error for expert, 1 policy_error for act@step_1000
    recs += [EpisodeRecord("eval1", "push-t", "expert", "", None, 16 + j, 0, "sim", False, "sim_error")
             for j in range(2)]
    recs.append(EpisodeRecord("eval1", "push-t", "act", "step_1000", 1000, 16, 0, "sim", False,
                              "policy_error"))
    # one video that does not exist on disk
    recs.append(EpisodeRecord("eval1", "push-t", "act", "step_5000", 5000, 20, 0, "sim", False, "sim_error",
                              video_path=str(tmp / "gone.mp4")))
    k_real = TRUTH[("act", "step_20000", 20000)][1]
    for i in range(N_REAL):
        real_ok = i < k_real
        recs.append(EpisodeRecord("eval1", "push-t", "act", "step_20000", 20000, i, 0, "replay",
                                  real_ok != (i in REPLAY_FLIPS), "ok"))
    store.record_episodes(recs)
    store.start_run("real", "push-t", {"kind": "real-robot outcomes", "task": "push-t"})
    return store


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    store = build_store(tmp)
    out = write_report(store, "eval1", tmp / "out" / "report.html", real_run_id="real")
    return store, out, out.read_text()


def _text(page: str) -> str:
    return re.sub(r"<[^>]+>", " ", page)


def test_summarize_keeps_errors_apart(report):
    store, _, _ = report
    cells = summarize(store.episodes("eval1", domain="sim"))
    expert = cells[("expert", "")]
    assert (expert.ok, expert.successes, expert.sim_error, expert.policy_error) == (16, 15, 2, 0)
    act = cells[("act", "step_1000")]
    assert (act.ok, act.successes, act.policy_error) == (16, 3, 1)
    assert act.train_step == 1000
    # sorted by policy, then train step
    assert list(cells)[:3] == [("act", "step_1000"), ("act", "step_5000"), ("act", "step_20000")]


def test_report_numbers(report):
    _, out, page = report
    text = _text(page)
    assert out.name == "report.html" and page.startswith("<!DOCTYPE html>")
    # success table: expert 15/16 -> 93.8%, Clopper-Pearson interval of 15/16
    lo, hi = metrics.clopper_pearson(15, 16)
    assert "93.8%" in text and f"[{100 * lo:.1f}%, {100 * hi:.1f}%]" in text
    # sim vs real statistics over the six pairs
    keys = list(TRUTH)
    s = [TRUTH[k][0] / N_SIM for k in keys]
    r = [TRUTH[k][1] / N_REAL for k in keys]
    pr = metrics.pearson(sim=s, real=r)
    assert f"{pr.r:.3f} [{pr.low:.3f}, {pr.high:.3f}]" in text
    outcomes = {k: ([1] * TRUTH[k][0] + [0] * (N_SIM - TRUTH[k][0]),
                    [1] * TRUTH[k][1] + [0] * (N_REAL - TRUTH[k][1])) for k in keys}
    mm = metrics.mmrv_bootstrap(sim=[outcomes[k][0] for k in keys], real=[outcomes[k][1] for k in keys],
                                n_boot=2000, seed=0)
    assert mm.value == pytest.approx(metrics.mmrv(sim=s, real=r))
    assert f"{mm.value:.3f} [{mm.low:.3f}, {mm.high:.3f}]" in text
    # replay confusion for act@step_20000: real successes at init 0..5; flips at 2 (S->F) and 7 (F->S)
    # -> [[real S & replay S, real S & replay F], [real F & replay S, real F & replay F]] = [[5, 1], [1, 3]]
    cm = re.search(r"<h3>act @ step_20000</h3>(.*?)</table>", page, re.S).group(1)
    assert re.findall(r">(\d+)</td>", cm) == ["5", "1", "1", "3"]
    assert "10 paired episodes, agreement 80.0%" in text and "found no partner" not in text
    # status counts, protocol, videos
    assert "sim_error" in text and "policy_error" in text
    assert "warp-lang" in text and "initial states used" in text and "19: 0-17, 20" in text
    assert page.count("<video") == 2 and page.count("data:video/mp4;base64,") == 2
    assert "missing video file" in text and "gone.mp4" in text
    assert page.count("<img") == 4  # bar plot, scatter, curves, violins
    assert "http://" not in page and "https://" not in page  # self-contained


def test_report_notes_without_real(tmp_path, report):
    store, _, _ = report
    page = write_report(store, "eval1", tmp_path / "r.html", real_run_id=None,
                        videos=VideoLimits(max_videos=1)).read_text()
    assert "No real outcomes found" in page
    assert "10 replay episodes but no real outcomes to pair with" in page
    assert "more videos not embedded (cap: 1 videos)" in page
    small = VideoLimits(max_bytes_each=1000)
    page = write_report(store, "eval1", tmp_path / "r1.html", videos=small).read_text()
    assert page.count("<video") == 0 and page.count("not embedded: size cap 1 KiB each") == 2
    page = write_report(store, "eval1", tmp_path / "r2.html", real_run_id="nope").read_text()
    assert "run &#x27;nope&#x27; is not in the store" in page
    with pytest.raises(ValueError, match="run 'missing' not found"):
        write_report(store, "missing", tmp_path / "x.html")


def test_report_pearson_undefined_is_explained(tmp_path):
    store = ResultsStore(tmp_path / "s.sqlite")
    recs = []
    for p, (ks, kr) in {"a": (4, 1), "b": (4, 3)}.items():
        recs += [EpisodeRecord("e", "push-t", p, "", None, i, 0, "sim", i < ks, "ok") for i in range(4)]
        recs += [EpisodeRecord("r", "push-t", p, "", None, i, 0, "real", i < kr, "ok") for i in range(4)]
    store.record_episodes(recs)
    text = _text(write_report(store, "e", tmp_path / "r.html", real_run_id="r").read_text())
    assert "undefined: Pearson r needs at least 3 paired policies, got 2" in text
    # both sim rates are 1.0 (a tie), real 0.25 vs 0.75: MMRV = (0 + 0.5) / 2
    assert "0.250 [" in text
    assert "No episode has a train_step" in text and "registered protocol" in text


def test_replay_run_pairs_with_its_own_real_records(tmp_path):
    # layout written by `twinbench replay`: run "replay" holds (real, replay) records with the recorded
    # episodes' seeds; run "real" holds CSV outcomes of the same init states with other seeds
    store = ResultsStore(tmp_path / "s.sqlite")
    recs = [EpisodeRecord("ev", "push-t", "act", "", None, i, 0, "sim", i < 3, "ok") for i in range(4)]
    recs += [EpisodeRecord("real", "push-t", "act", "", None, i, 0, "real", True, "ok") for i in range(4)]
    real_ok = [True, True, False, False]
    replay_ok = [True, False, True, False]
    for i in range(4):
        recs.append(EpisodeRecord("replay", "push-t", "act", "", None, i, 100 + i, "real", real_ok[i], "ok"))
        recs.append(EpisodeRecord("replay", "push-t", "act", "", None, i, 100 + i, "replay", replay_ok[i],
                                  "ok"))
    store.record_episodes(recs)
    out = write_report(store, "ev", tmp_path / "r.html", real_run_id="real", replay_run_id="replay")
    page = out.read_text()
    cm = re.search(r"<h3>act</h3>(.*?)</table>", page, re.S).group(1)
    # paired with the replay run's own real records (1 S/S, 1 S/F, 1 F/S, 1 F/F), not the CSV ones
    assert re.findall(r">(\d+)</td>", cm) == ["1", "1", "1", "1"]
    assert "found no partner" not in page
    # without the replay run: no replay section content
    page = write_report(store, "ev", tmp_path / "r2.html", real_run_id="real").read_text()
    assert "No replay episodes" in page


def test_pair_replay_by_key_then_seed():
    def rec(domain, init, seed, ok=True, status="ok"):
        return EpisodeRecord("x", "t", "p", "c", None, init, seed, domain, ok, status)

    replay = [rec("replay", 0, 0), rec("replay", 1, 5), rec("replay", 1, 6),
              rec("replay", 2, 0, status="sim_error")]
    real = [rec("real", 0, 9), rec("real", 1, 6), rec("real", 1, 7), rec("real", 2, 0), rec("real", 3, 0)]
    pairs, n_rp, n_rl = pair_replay(replay, real)
    # init 0: one on each side, paired despite different seeds; init 1: seed 6 pairs; 5 and 7 do not
    assert [(a.init_state, a.seed, b.seed) for a, b in pairs] == [(0, 0, 9), (1, 6, 6)]
    assert (n_rp, n_rl) == (1, 3)  # replay seed 5; real seed 7, init 2 (replay errored), init 3


def test_cli_report(tmp_path, report):
    store, _, _ = report
    out = tmp_path / "cli.html"
    assert cli_main(["report", "--run-id", "eval1", "--db", str(store.path), "--out", str(out),
                     "--max-videos", "0"]) == 0
    assert "Sim vs real" in out.read_text()
    assert cli_main(["report", "--run-id", "nope", "--db", str(store.path), "--out", str(out)]) == 2


@pytest.mark.skipif(not Path(CHROMIUM).exists(),
                    reason=f"{CHROMIUM} not installed (CI: apt-get install -y chromium)")
def test_report_in_headless_chromium(report, tmp_path):
    _, out, _ = report
    shot = tmp_path / "report.png"
    res = check_page(out, shot)
    assert res.errors == []
    assert len(res.images) == 4 and all(i["complete"] and i["naturalWidth"] > 0 for i in res.images)
    assert len(res.videos) == 2
    for v in res.videos:
        assert v["readyState"] >= 1 and v["error"] is None and v["videoWidth"] == 64
    png = iio.imread(shot)
    assert png.shape[1] == 1280 and png.shape[0] == res.height > 2000
    assert res.title == "twinbench report — eval1"


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"{CHROMIUM} not installed")
def test_browser_check_sees_errors_and_broken_media(tmp_path):
    # the checker itself must catch what the report test relies on it to catch
    page = tmp_path / "bad.html"
    page.write_text('<!DOCTYPE html><html><head><link rel="icon" href="data:,"></head><body>'
                    '<img alt="broken" src="data:image/png;base64,AAAA">'
                    '<video src="data:video/mp4;base64,AAAA"></video>'
                    '<script>console.error("boom"); undefined_fn();</script></body></html>')
    res = check_page(page)
    assert any("boom" in e for e in res.errors) and any("undefined_fn" in e for e in res.errors)
    assert res.images[0]["naturalWidth"] == 0
    assert res.videos[0]["error"] is not None


def test_success_table_shows_train_step_zero(tmp_path):
    # expert@1.0 is train step 0: shown as 0 (not "–") whether or not the cell has ok episodes
    store = ResultsStore(tmp_path / "s.sqlite")
    store.record_episodes(
        [EpisodeRecord("e", "point-reach", "expert", "step_0", 0, i, i, "sim", False, "sim_error")
         for i in range(2)]
        + [EpisodeRecord("e", "point-reach", "noisy", "step_0", 0, i, i, "sim", i == 0, "ok")
           for i in range(2)])
    page = write_report(store, "e", tmp_path / "r.html", real_run_id=None).read_text()
    assert "<tr><td>expert</td><td>step_0</td><td>0</td><td>0</td><td>0</td><td>–</td>" in page
    assert "<tr><td>noisy</td><td>step_0</td><td>0</td><td>2</td><td>1</td><td><b>50.0%</b></td>" in page


def test_real_rows_of_another_task_or_grid_are_flagged_loudly(tmp_path, capsys):
    store = ResultsStore(tmp_path / "r.sqlite")
    grid = {"task": "point-reach", "n_states": 8, "id": "point-reach-8"}
    store.start_run("sim", "point-reach", {"task": "point-reach", "grid": grid})
    store.record_episodes([EpisodeRecord("sim", "point-reach", "expert", "", None, i, 0, "sim", i < 6, "ok")
                           for i in range(8)])
    store.start_run_with_episodes("real", "push-t", {"task": "push-t"}, [
        EpisodeRecord("real", "push-t", "expert", "", None, i, 0, "real", True, "ok") for i in range(5)])
    out = tmp_path / "rep.html"
    assert cli_main(["report", "--run-id", "sim", "--db", str(store.path), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert ("WARNING: episodes of another task are left out of every comparison: 5 real of task "
            "'push-t'") in err
    page = out.read_text()
    assert page.count('<div class="warn">Warning: episodes of another task') == 1
    assert "Real outcomes exist" not in page and "No real outcomes found" in page  # none compared
    assert cli_main(["report", "--run-id", "sim", "--db", str(store.path), "--out", str(out),
                     "--strict"]) == 2
    assert "do not pair with run 'sim'" in capsys.readouterr().err
    # the same task on another grid: kept, but flagged
    other = {"task": "point-reach", "grid": {**grid, "id": "x"}}
    store.start_run_with_episodes("real2", "point-reach", other, [
        EpisodeRecord("real2", "point-reach", "expert", "", None, i, 0, "real", True, "ok")
        for i in range(4)])
    warned = []
    write_report(store, "sim", out, real_run_id="real2", warn=warned.append)
    assert len(warned) == 1 and "run 'real2' indexes another initial-state grid" in warned[0]
    assert "Warning: run &#x27;real2&#x27; indexes another" in out.read_text()
    with pytest.raises(ValueError, match="another initial-state grid"):
        write_report(store, "sim", out, real_run_id="real2", strict=True)
    # same grid: no warning
    store.start_run("real3", "point-reach", {"task": "point-reach", "grid": grid})
    warned.clear()
    write_report(store, "sim", out, real_run_id="real3", warn=warned.append)
    assert warned == [] and 'class="warn"' not in out.read_text()


def test_training_curve_tick_labels_are_compact():
    from twinbench.evaluation.report import _step_label

    assert [_step_label(v) for v in (0, 500, 20000, 25000, 1_500_000)] == ["0", "500", "20k", "25k", "1.5M"]

"""End to end: the demo job (push-T evaluation + report) on one grid state, in this process."""

from twinbench.commands.demo import DemoConfig, main
from twinbench.evaluation.store import ResultsStore


def test_demo_evaluates_writes_videos_and_report(tmp_path, capsys):
    cfg = DemoConfig(out_dir=tmp_path, episodes="grid:5", policies=("expert",), workers=0)
    assert main(cfg) == 0
    out = capsys.readouterr().out
    (rec,) = ResultsStore(tmp_path / "results.sqlite").episodes("demo")
    assert rec.task == "push-t" and rec.init_state == 5 and rec.status == "ok" and rec.success
    video = tmp_path / "videos" / "demo" / "expert" / "init5_seed5.mp4"
    assert video.stat().st_size > 10_000 and str(video) in out
    html = (tmp_path / "report.html").read_text()
    assert "push-t" in html and "data:video/mp4;base64," in html
    assert main(cfg) == 0  # a second run resumes: nothing left to do
    assert "0 to run" in capsys.readouterr().out

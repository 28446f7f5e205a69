"""The CLI's stdout is what the user asked for: no Warp banner or module-load lines, in-process or in
worker processes."""

import subprocess
import sys


def test_eval_stdout_has_no_warp_lines(tmp_path):
    for workers in ("0", "1"):
        out = subprocess.run(
            [sys.executable, "-m", "twinbench.cli", "eval", "--task", "push-t", "--policy", "expert",
             "--episodes", "grid:0", "--workers", workers, "--run-id", f"w{workers}", "--env-kwargs",
             '{"preset": "fast", "episode_seconds": 0.1, "settle_steps": 0}'],
            capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        assert "Warp " not in out.stdout and "Module " not in out.stdout, out.stdout
        assert "expert: 0/1 successes" in out.stdout + out.stderr

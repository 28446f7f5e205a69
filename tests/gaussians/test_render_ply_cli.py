"""`twinbench render-ply`: renders a written file, fails with one clear line on bad input."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from twinbench.cli import main
from twinbench.gaussians.camera import framing_camera
from twinbench.gaussians.io import save_gaussians


def test_render_ply_writes_a_png_that_frames_the_cloud(tmp_path, make_cloud):
    cloud = make_cloud(400, degree=1, seed=2, center=(5.0, -3.0, 1.0), spread=0.5, log_scale=(-3.5, -2.5))
    cloud.logit_opacities[:] = 4.0
    for ext in (".ply", ".splat", ".spz"):
        src = tmp_path / f"scene{ext}"
        save_gaussians(cloud, src)
        out = tmp_path / f"img{ext}.png"
        assert main(["render-ply", str(src), "--out", str(out), "--width", "80", "--height", "60"]) == 0
        img = iio.imread(out)
        assert img.shape == (60, 80, 3) and img.dtype == np.uint8
        lit = img.max(axis=2) > 0
        # the cloud is in view, centred, and not cut off by the image border
        assert lit.mean() > 0.1
        ys, xs = np.nonzero(lit)
        assert abs(xs.mean() - 40) < 8 and abs(ys.mean() - 30) < 8
        assert not lit[:, 0].any() and not lit[:, -1].any()


def test_framing_camera_fits_the_percentile_sphere(make_cloud):
    cloud = make_cloud(1000, seed=1, spread=1.0)
    cam = framing_camera(cloud, width=100, height=50, fov_deg=90)
    w2c = cam.world_to_cam
    p = cloud.means @ w2c[:3, :3].T + w2c[:3, 3]
    u = cam.fx * p[:, 0] / p[:, 2] + cam.cx
    v = cam.fy * p[:, 1] / p[:, 2] + cam.cy
    inside = (u >= 0) & (u < 100) & (v >= 0) & (v < 50) & (p[:, 2] > 0)
    assert inside.mean() >= 0.95


def test_render_ply_bad_file_exits_nonzero_with_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n")
    assert main(["render-ply", str(bad), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.ply" in err[0] and "missing vertex properties" in err[0]
    assert "Traceback" not in err[0]
    assert not (tmp_path / "x.png").exists()

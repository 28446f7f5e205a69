"""twinbench.gaussians: 3D Gaussian Splatting data, file formats, rendering and skinning.

Modules (imported on demand, so `import twinbench.gaussians` stays light):
  cloud     GaussianCloud (host arrays), DeviceGaussians (Warp arrays), quaternion helpers
  camera    Camera (OpenCV pinhole + cam_to_world), framing_camera (a view that fits a cloud)
  io        load_gaussians / save_gaussians (.ply, .splat, .spz), GaussianFileError
  render    render(cloud, cameras, ..., backend=) -> RenderOutput; render_batch([(cloud, camera), ...])
            renders many views (e.g. every world's cameras) in one call; backends are a registry
            (register_backend, backends): "warp" (warp_raster: Warp tiles on CPU/CUDA), "gsplat"
            (gsplat_backend: CUDA, extra `gsplat`), "reference" (reference: brute-force NumPy);
            RenderCache + SplitGaussians(static, moving): a still camera's static work kept between renders
  render_rules  the rules every backend renders by (DESIGN §6) and RenderOutput
  skinning  bind / LBSSkinner / skin (LBS) and LabelRigidPoser (per-label or whole-cloud rigid motion)
  sh        real spherical harmonics and their rotation
"""

"""twinbench.gaussians: 3D Gaussian Splatting data, file formats, rendering and skinning.

Modules (imported on demand, so `import twinbench.gaussians` stays light):
  cloud     GaussianCloud (host arrays), DeviceGaussians (Warp arrays), quaternion helpers
  camera    Camera (OpenCV pinhole + cam_to_world)
  io        load_gaussians / save_gaussians (.ply, .splat, .spz), GaussianFileError
  render    render(cloud, cameras, ...) -> RenderOutput (Warp tiles on CPU/CUDA, gsplat on CUDA);
            render_batch([(cloud, camera), ...]) renders many views (e.g. every world's cameras) in one call
  skinning  bind / LBSSkinner / skin (LBS) and LabelRigidPoser (per-label or whole-cloud rigid motion)
  sh        real spherical harmonics and their rotation
"""

"""twinbench.construct: the real-to-sim tools that turn scans and recordings into twin data (DESIGN §1
steps 2-5). Each module is imported on its own (this package imports nothing):

    segment          crop boxes split a workcell scan into robot / background / objects
    align_robot      RANSAC + ICP registration of the robot's Gaussians to its URDF, link labels
    align_color      the rendered -> real colour map (IRLS, Tukey), rendered/real image pairs
    calibration      camera calibration files -> CameraSpecs
    phystwin         PhysTwin cases: restricted loader, import as a twin object, export back
    mesh_object      a rigid spring-mass object with surface Gaussians from a closed mesh
    rigid_layout     a rigid object's recorded motion carried onto another particle layout of it
    build_config     a TwinSpec / twin directory from a build config naming the steps' outputs
    sysid_io         system identification's input files and the identified object directory
    sysid_report     system identification's fit report (JSON + PNG)
    sysid_synthetic  a synthetic system-identification case with known answers

The fit itself is `twinbench.physics.sysid`; the commands are in `twinbench.commands`.
"""

"""A rigid object's recorded motion carried onto another particle layout of the same object (its task's
lattice, a CAD model's `mesh_object`): the tracked points' rigid motion, fitted frame by frame, moves every
particle of the layout, which becomes the system-identification input's particles and tracks.

    data = relayout(load_sysid_data("motion/tblock-push"), lattice_world, masses)

A tracker's points are where the cameras saw texture, not where the body's mass is; for a body the task
declares rigid the layout can be its known shape instead, and every particle's path follows from the
tracks (a least-squares rigid transform per frame, one trimming pass against unreliable tracks).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from twinbench.physics.sysid_data import SysIdData, SysIdFormatError
from twinbench.transforms import fit_rigid_transform, transform_points

MIN_TRACKS = 3  # tracks seen at frame 0 and at frame k needed to fit frame k's motion
TRIM = 3.0  # a track off the first fit by more than TRIM x the median residual (and 1 mm) is left out


def rigid_motion(data: SysIdData) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the rigid transform (world frame) carrying the tracked points from frame 0 to that frame,
    fitted on the tracks valid at both (trimmed once), and whether it could be fitted (at least MIN_TRACKS
    tracks): ((F, 4, 4), (F,) bool). Frame 0 is the identity."""
    frames = len(data.tracked)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    ok = np.zeros(frames, bool)
    ok[0] = True
    start = data.tracked[0]
    for k in range(1, frames):
        seen = data.motion_valid[0] & data.motion_valid[k]
        if seen.sum() < MIN_TRACKS:
            continue
        src, dst = start[seen], data.tracked[k][seen]
        pose = fit_rigid_transform(src, dst)
        residual = np.linalg.norm(transform_points(pose, src) - dst, axis=1)
        keep = residual <= max(TRIM * float(np.median(residual)), 1e-3)
        if keep.sum() >= MIN_TRACKS and not keep.all():
            pose = fit_rigid_transform(src[keep], dst[keep])
        poses[k], ok[k] = pose, True
    return poses, ok


def relayout(data: SysIdData, particles: np.ndarray, masses: np.ndarray | None = None) -> SysIdData:
    """`data` with `particles` ((P, 3), world frame at frame 0: the layout placed where the object is at
    frame 0) as its particles, each tracked in every frame whose rigid motion the tracks give
    (`rigid_motion`; other frames invalid), `masses` ((P,) or None: 1 each) their masses; explicit springs
    and surface indices dropped (the radius rule on the new layout). The observed points, visibility,
    controls and tool stay."""
    particles = np.asarray(particles, np.float64)
    if particles.ndim != 2 or particles.shape[1] != 3 or not len(particles):
        raise ValueError(f"relayout: particles must be a non-empty (P, 3) array, got {particles.shape}")
    seen = int(data.motion_valid[0].sum())
    if seen < MIN_TRACKS:
        raise SysIdFormatError(f"{data.source}: motion_valid: {seen} tracks valid at frame 0; a rigid "
                               f"relayout needs at least {MIN_TRACKS}")
    poses, ok = rigid_motion(data)
    tracked = transform_points(poses, particles)
    valid = np.repeat(ok[:, None], len(particles), axis=1)
    return dataclasses.replace(data, particles=particles, tracked_indices=np.arange(len(particles)),
                               tracked=tracked, motion_valid=valid, springs=None, rest_lengths=None,
                               masses=masses, surface_indices=None)

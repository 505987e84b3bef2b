"""Embedded synthetic localisation benchmark: textured rooms seen by moving pinhole cameras.

The package is split at its seams: ``camera`` (pinhole model, pose conventions), ``scene``
(rooms, boxes, textures, camera routes), ``raycast`` (the renderer and the camera response),
``trajectories`` (train and test sequences), ``nuisances`` (optional lighting change,
occluders, sensor noise and motion blur), ``surfaces`` (optional plain, repeated and glossy
surfaces), ``capture`` (an optional camera pipeline, JPEG and larger images), ``writer``
(datasets on disk) and ``settings`` (every setting of a dataset, with its default and range);
every public name is importable from here, each module imported when a name of it is first
used (so that ``pae.synthetic.settings`` loads without numpy and torch).

Each scene is a room (an axis-aligned box seen from inside, a few metres wide like the
7-Scenes rooms) holding a few axis-aligned boxes and thin panels. Every face carries its own
procedural texture: large coloured gradients and shapes (so a 64 px view tells where the
camera is and where it looks) plus finer detail. Images are ray cast exactly in numpy,
with a point light and 2×2 supersampling, then pass through a per-sequence camera response
(gain, bias, tint, gamma, sensor noise). The pose can only be learnt from what the camera sees.
Nuisances, all off by default (:class:`Nuisances`), add what no scene model explains: lighting
and exposure changing between and within sequences, person-sized occluders in front of the
camera, more sensor noise and motion blur. Surfaces and capture of real data, all off by
default too (:class:`SurfaceOptions`, :class:`CaptureOptions`), take away what makes the
plain benchmark kind to render-and-compare: texture-poor, periodic and glossy surfaces,
vignetting, gamma, drifting auto-exposure and white balance, JPEG, images larger than the
compare width.

Conventions:

- World frame: metres, ``z`` up, floor at ``z = 0``, room centred on ``x = y = 0``.
- Poses ``[7]`` = ``x, y, z, qw, qx, qy, qz``, camera-to-world, ``qw >= 0``.
- Camera frame (OpenCV): ``x`` right, ``y`` down, looking along ``+z``.
- Pixels: the centre of pixel ``(u, v)`` (column, row) lies at integer coordinates ``(u, v)``;
  the principal point is the image centre ``((W - 1) / 2, (H - 1) / 2)`` and
  ``fx = fy = (W / 2) / tan(fov / 2)`` for the horizontal field of view ``fov``.
- Textures: texel ``(row i, column j)`` of a face covers face coordinates
  ``a ∈ [j·s, (j+1)·s)``, ``b ∈ [i·s, (i+1)·s)`` (texel size ``s`` metres); its centre is at
  ``((j + 0.5)·s, (i + 0.5)·s)``. Textures are sampled bilinearly between texel centres.

Layout written by :func:`write_synthetic_dataset` (label format of :mod:`pae.data.labels`)::

    OUT/labels/scene00_train.csv  OUT/labels/scene00_test.csv  ...  OUT/labels/all_{train,test}.csv
    OUT/scene00/seq-01/frame-000000.png  ...
    OUT/labels/nuisances.csv   (only with a nuisance or the camera pipeline on: img_path,
                                occluder_share, blur_px, exposure_gain per frame)
"""

from __future__ import annotations

from pae.core.lazy import lazy_attributes

_MODULES = {
    "DEFAULT_FOV_DEG": "pae.synthetic.camera",
    "DEFAULT_SIZE": "pae.synthetic.camera",
    "PinholeCamera": "pae.synthetic.camera",
    "pose_rotation_translation": "pae.synthetic.camera",
    "world_to_camera": "pae.synthetic.camera",
    "CaptureOptions": "pae.synthetic.settings",
    "JPEG_QUALITY_RANGE": "pae.synthetic.settings",
    "RENDER_SCALE_MAX": "pae.synthetic.settings",
    "sequence_capture": "pae.synthetic.capture",
    "MOTION_DEPTH_M": "pae.synthetic.nuisances",
    "NUISANCE_BOUNDS": "pae.synthetic.settings",
    "Nuisances": "pae.synthetic.settings",
    "OCCLUDER_DISTANCE_M": "pae.synthetic.nuisances",
    "OCCLUDER_SIZE_M": "pae.synthetic.nuisances",
    "person_textures": "pae.synthetic.nuisances",
    "sequence_nuisances": "pae.synthetic.nuisances",
    "AUTO_EXPOSURE_RANGE": "pae.synthetic.raycast",
    "AUTO_EXPOSURE_TARGET": "pae.synthetic.raycast",
    "Appearance": "pae.synthetic.raycast",
    "FrameConditions": "pae.synthetic.raycast",
    "RAYS_PER_CHUNK": "pae.synthetic.raycast",
    "SUPERSAMPLE": "pae.synthetic.raycast",
    "jpeg_roundtrip": "pae.synthetic.raycast",
    "motion_kernel": "pae.synthetic.raycast",
    "render": "pae.synthetic.raycast",
    "render_batch": "pae.synthetic.raycast",
    "shade_rays": "pae.synthetic.raycast",
    "vignette": "pae.synthetic.raycast",
    "Box": "pae.synthetic.scene",
    "CameraRoute": "pae.synthetic.scene",
    "FaceTexture": "pae.synthetic.scene",
    "SyntheticScene": "pae.synthetic.scene",
    "TEXEL_SIZE_M": "pae.synthetic.scene",
    "furnish": "pae.synthetic.scene",
    "make_scene": "pae.synthetic.scene",
    "room_textures": "pae.synthetic.scene",
    "scene_name": "pae.synthetic.scene",
    "SyntheticSettings": "pae.synthetic.settings",
    "REPEAT_PERIOD_M": "pae.synthetic.surfaces",
    "SURFACE_BOUNDS": "pae.synthetic.settings",
    "SurfaceOptions": "pae.synthetic.settings",
    "dress_surfaces": "pae.synthetic.surfaces",
    "CameraSequence": "pae.synthetic.trajectories",
    "TEST_SEQUENCES": "pae.synthetic.trajectories",
    "TRAIN_SEQUENCES": "pae.synthetic.trajectories",
    "make_sequences": "pae.synthetic.trajectories",
    "FRAMES_PER_WRITE": "pae.synthetic.writer",
    "NUISANCE_COLUMNS": "pae.synthetic.writer",
    "NUISANCE_FILE": "pae.synthetic.writer",
    "RenderProgress": "pae.synthetic.writer",
    "SyntheticSummary": "pae.synthetic.writer",
    "render_frames": "pae.synthetic.writer",
    "render_sequence": "pae.synthetic.writer",
    "scaled_blur": "pae.synthetic.writer",
    "sequence_conditions": "pae.synthetic.writer",
    "surface_seed": "pae.synthetic.writer",
    "write_label_files": "pae.synthetic.writer",
    "write_nuisance_table": "pae.synthetic.writer",
    "write_synthetic_dataset": "pae.synthetic.writer",
    "write_whole": "pae.synthetic.writer",
}
"""Each public name -> the module of ``pae.synthetic`` that defines it."""

__all__ = sorted(_MODULES)

__getattr__ = lazy_attributes(__name__, _MODULES)

"""GCVD test-time optimisation (pure functions: arrays in, arrays out, no file I/O).

Modules in data-path order:

- ``params``: the parameters of all three optimisations, declared once (the pipeline's config
  sections are derived from them);
- ``frames``: inputs brought to the loss resolution, depth read out at working resolution;
- ``init``: initial poses and depths (essential-matrix chain, two-view pose, PnP, depth transfer);
- ``losses``: the sampled-point loss terms;
- ``solver``: the per-window Adam solver shared by the stages, determinism, checkpoint helpers;
- ``keyframes``: ``optimize_keyframes``, sliding windows over the keyframes;
- ``edges``: ``optimize_edge``, the relative pose of a loop (non-sequential) keyframe pair;
- ``pose_graph``: ``optimize_pose_graph``, keyframe pose graph (gtsam LM);
- ``segments``: ``optimize_segments``, all frames with the keyframe poses frozen.

Pose convention: poses are T_w_c (camera-to-world 4x4 float64, OpenCV axes); the relative pose
mapping camera-a coordinates into camera-b coordinates is T_b_a = inv(T_w_b) @ T_w_a.
"""

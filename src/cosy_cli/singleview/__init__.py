"""Single-view pose estimation (CosyPose stage 1): detections in, object candidates out.

- ``estimate_stage``: ``cosy estimate``, the one place that chooses among the two paths.
- ``networks``: the render-and-compare networks of the paper (Appendix A): crops and the coarse
  model's canonical pose (``crops``), the pose update F (``pose_update``), the disentangled
  symmetric L1 loss (``losses``), ``PoseNet`` (``model``), ONNX export and runner (``onnx``), the
  coarse/refiner inference loop (``render_compare``), CosyPose's published checkpoints
  (``cosypose_compat``).
- ``training_free``: template retrieval (``templates``), verification by rendering
  (``verify``), contour alignment (``contour``), depth ICP (``icp``) and its near-symmetry
  hypotheses (``depth_hypotheses``).
"""

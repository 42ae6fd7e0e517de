"""Single-view pose estimation (paper Appendix A): render-and-compare coarse and refiner networks.

- ``crops``: the cropping strategy (crop centred on the projected object origin, sized from the
  projected model points, enlarged and fitted to the network aspect ratio) and the coarse model's
  canonical input pose.
- ``pose_update``: the DeepIM/CosyPose update F(T^k, [v_x, v_y, v_z], R) and its inverse (torch).
- ``losses``: the disentangled symmetric L1 point loss (torch).
- ``model``: ``PoseNet`` (EfficientNet backbone + linear head, 9 outputs).
- ``onnx``: export to ONNX and an onnxruntime runner.
"""

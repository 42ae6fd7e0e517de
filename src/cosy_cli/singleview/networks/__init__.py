"""The render-and-compare networks of CosyPose (paper Appendix A): crops, pose update, loss, PoseNet, ONNX, the published CosyPose checkpoints."""

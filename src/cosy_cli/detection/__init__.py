"""2D object detection: the trainable detector (an anchor-free centre-heatmap network trained on
on-the-fly renders, exported to ONNX and run with onnxruntime), box utilities (IoU, NMS).

Imports stay light: nothing heavy (torch, onnxruntime, OpenGL) is imported with this package.

- :mod:`.boxes`: ``box_iou``, ``nms``, ``nms_per_class`` (numpy, boxes [x, y, w, h] px);
- :mod:`.model`: ``CenterNet`` and its ``DetectorConfig``, target encoding and decoding;
- :mod:`.data`: ``DetectionSampleGenerator``: random scenes of a dataset's objects, rendered;
- :mod:`.train`: ``cosy train detector`` and the detector's ONNX export;
- :mod:`.network`: ``OnnxDetector``, the runner of an exported detector.
"""

"""Object detection: ONNX Runtime YOLOv8/YOLOX detectors and the simulator's oracle."""

"""cmnav export: trained checkpoints (and the goal-seeker plumbing model) -> the runtime's ONNX file."""

"""pallet6d.export: torch model definitions, losses, training, ONNX export and int8 quantization."""

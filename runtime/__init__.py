"""pallet6d.runtime: everything that runs on the forklift (numpy + onnxruntime + OpenCV, never torch)."""

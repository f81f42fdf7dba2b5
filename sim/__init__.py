"""pallet6d.sim: synthetic warehouse RGB-D scenes with exact ground truth, in the BOP format."""

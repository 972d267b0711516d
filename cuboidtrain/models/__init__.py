"""The three networks, the registry of architectures, the keypoint codec and PDM, and the files that hold them."""

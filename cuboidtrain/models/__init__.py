"""The three networks, the registry of architectures, and the files that hold them."""

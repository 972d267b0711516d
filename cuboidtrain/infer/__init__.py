"""Running `cuboidtrain infer` over many inputs: gathering them, fitting them in a pool or on a cluster,
the record file, progress, and the writers (explanation panels, meshes, ONNX export)."""

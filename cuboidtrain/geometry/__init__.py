"""The geometric solver: the cuboid's camera parameters, lifting corners to 3D, fitting a mask, 3D IoU, error scores.

Numbers in, numbers out: nothing here knows a network, a file or a command. The fit
pipeline (`cuboidtrain.fit`) and the scoring of `eval` stand on it.
"""

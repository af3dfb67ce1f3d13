"""DeMoN's multi-view HDF5 benchmarks (Scenes11, SUN3D, RGB-D SLAM) and a robot's own recordings.

`reader` decodes the files, `pairs` turns view pairs into `gld.records` examples
with damage accounting, `demon_dataset_builder` is the TFDS builder
(`demon/scenes11|sun3d|rgbd|custom`). `recordings` reads a robot's own recording,
`writer` writes it in the format, and `convert` is the command line over the two.
"""

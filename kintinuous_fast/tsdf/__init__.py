"""The TSDF and colour volume and its integration (kintinuous_ref.tsdf) for the cpu and cuda
backends.

    voxel.py          the stored int16 voxel, trilinear sampling, gradient normals, both targets
    ops.py            one voxel's integration and a pixel's colour weight, both targets
    volume.py         FastTsdfVolume (8 bytes per voxel), its conversions to and from the
                      reference's TsdfVolume, the moving volume's view of it
    cpu.py            the loop over voxel columns; cpu_culling.py: the bricks it leaves out
    cuda.py           one thread per voxel column
"""

"""Colour fusion's per-pixel weights (kintinuous_ref.colour, paper VI-B) for the cpu and cuda
backends: cpu.py and cuda.py, one loop or kernel each around tsdf.ops.colour_weight.
"""

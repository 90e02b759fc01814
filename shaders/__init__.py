"""Taichi rendering kernels: a software rasterizer that runs on CPU and GPU."""

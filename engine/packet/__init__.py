"""Large ray packets: packet layout, the shared packet-traversal kernels, frustum build and cull, 4-lane SIMD helpers."""

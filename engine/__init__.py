"""packetrt's shared core: contracts, scene model, BVH, kernels, Whitted loop, config, CLI."""

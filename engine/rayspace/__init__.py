"""Roger et al.'s ray-space hierarchy: cone-sphere nodes, (node, triangle) pair streams, triangle bounding spheres."""

"""Scene catalog, loaders (.aff, OBJ/PLY through trimesh) and procedural generators."""

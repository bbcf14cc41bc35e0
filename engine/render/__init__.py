"""The frame: config, the Tracer (the one place a batch is traced), the Whitted loop, shading and image output."""

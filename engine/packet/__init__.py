"""Large ray packets: packet layout, the one packet walk and its per-strategy steps, frustum build
and cull, 4-lane SIMD helpers."""

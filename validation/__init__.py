"""Ground truth: the Embree oracle, tie-aware hit comparison and the audit of a render."""

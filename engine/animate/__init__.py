"""``packetrt animate``: a BART animation path rendered in one process (frames, preview, stats)."""

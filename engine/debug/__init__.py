"""Pictures for people: `packetrt show` (one packet), `packetrt view` (live window), packet traces."""

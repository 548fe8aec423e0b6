"""nefii beside a peer system, Mitsuba 3 inverse rendering: ``python -m benchmarks.peers.mitsuba_inverse``."""

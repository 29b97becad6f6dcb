"""Sessions: one simulation source, its shared render state and the clients watching it."""

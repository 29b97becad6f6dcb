"""Structure and trajectory files read into protocol topologies and positions.

Shared by the server (REST renders, jobs, layers) and the adapters (replay, IMD), so a file one
of them accepts, all of them accept. MDAnalysis and gemmi are imported lazily.
"""

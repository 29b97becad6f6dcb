"""Client side of scalesteer: the connection to the render server and the adapters that feed it.

The base package imports only numpy, msgpack, pydantic and websockets; adapters that need an
MD package (OpenMM, MDAnalysis, imdclient) import it inside their own module.
"""

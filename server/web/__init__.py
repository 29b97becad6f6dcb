"""The web edge: the FastAPI app, its REST routes and WebSocket endpoints, auth and middleware.

Requests come in here and go down to the sessions (`server.session`) and the pipeline
(`server.pipeline`); nothing below imports this package.
"""

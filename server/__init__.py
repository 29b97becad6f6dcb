"""scalesteer's render server: sessions, GPU rendering, encoding, REST jobs and the CLI.

Importing `server` is cheap; heavy parts (warp-lang, FastAPI) load in their own modules.
"""

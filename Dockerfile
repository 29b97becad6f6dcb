# Render server image: CUDA runtime + the project with the server extra.
FROM nvidia/cuda:12.6.3-runtime-ubuntu24.04
ENV DEBIAN_FRONTEND=noninteractive PIP_NO_CACHE_DIR=1
RUN apt-get update && apt-get install -y --no-install-recommends python3 python3-venv nodejs npm \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY protocol protocol
COPY server server
COPY simulation_adapters simulation_adapters
COPY structures structures
COPY client_web client_web
RUN python3 -m venv /opt/venv && /opt/venv/bin/pip install ".[server,openmm,replay,imd,movies,ray]" \
    && if [ -f client_web/package.json ]; then cd client_web && npm ci --omit=dev; fi
ENV PATH=/opt/venv/bin:$PATH
EXPOSE 8000
# exec: the server is the container's process 1 and gets `docker stop`'s SIGTERM itself
CMD ["sh", "-c", "exec scalesteer serve --host 0.0.0.0 --port 8000 --device auto --token \"$SCALESTEER_TOKEN\" --data-dir /data"]

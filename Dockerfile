# One image for both sides of the pan-tilt demo (docker-compose.yml runs it twice):
#   rlbridge demo --role bridge       the middleware side: bridge server + vision node
#   rlbridge demo --role controller   the embedded side: the 1 kHz loop controller
#
# Build:  docker build -t rlbridge-demo .
# Try:    docker run --rm rlbridge-demo rlbridge demo --seconds 5 --no-plot
#
# Only pyproject.toml, README.md and src/ are copied, so the build context's .venv and caches
# do not end up in the image.
FROM python:3.11-slim

# iproute2 brings `tc`, used by the optional impaired-link service (profile "impaired").
# apt-get clean: the official image's apt config drops downloaded .debs, another base may not.
RUN apt-get update \
    && apt-get install -y --no-install-recommends iproute2 \
    && apt-get clean && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/rlbridge
COPY pyproject.toml README.md ./
COPY src ./src
# [plot]: matplotlib for the end-of-run PNG. No ROS 2 here: the middleware is the in-process bus.
RUN pip install --no-cache-dir ".[plot]"

ENV PYTHONUNBUFFERED=1
# No HEALTHCHECK here: what "healthy" means depends on the role, so docker-compose.yml gives
# the bridge service `rlbridge ping --port 7411` (exit 0 when the server answers).
EXPOSE 7411/tcp 7411/udp
CMD ["rlbridge", "demo", "--seconds", "5", "--no-plot"]

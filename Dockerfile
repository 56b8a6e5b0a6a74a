# One image for both sides of the pan-tilt demo (docker-compose.yml runs it twice):
#   rlbridge demo --role bridge       the middleware side: bridge server + vision node
#   rlbridge demo --role controller   the embedded side: the 1 kHz loop controller
#
# Build:  docker build -t rlbridge-demo .
# Try:    docker run --rm rlbridge-demo rlbridge demo --seconds 5 --no-plot
#         docker run --rm rlbridge-demo rlbridge --version
#
# What the image runs: the value path compiled by mypyc and sealed sessions (the demo's
# pre-shared key) on libsodium's ChaCha20-Poly1305 (rlbridge.wire._chacha); `rlbridge --version`
# says so, and the build fails if either is missing rather than ship the slower fallback.
# Two stages: "build" has the compiler, the Python and libsodium headers and mypy (pip's
# isolated build environment) and installs rlbridge with its dependencies under /install; the
# image gets that tree in its /usr/local (where the base's Python looks), iproute2 and
# libsodium's runtime library, none of the build tools.
# Only pyproject.toml, README.md, setup.py and src/ are copied, so the build context's .venv and
# caches do not end up in the image (.dockerignore keeps them out of the context too).
FROM python:3.11-slim AS build

# gcc and libc6-dev compile the extensions, libsodium-dev has sodium.h. The official image has
# Python's headers in /usr/local/include; a base whose python3 is Debian's (a virtualenv over
# /usr/bin/python3) has none until python3-dev. Without them setup.py would install the pure
# package (the check in the image's stage below then fails the build).
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev libsodium-dev \
    && include="$(python3 -c 'import sysconfig; print(sysconfig.get_paths()["include"])')" \
    && if [ ! -e "$include/Python.h" ]; then \
         apt-get install -y --no-install-recommends python3-dev; fi \
    && apt-get clean && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/rlbridge
COPY pyproject.toml README.md setup.py ./
COPY src ./src
# [plot]: matplotlib for the end-of-run PNG. No ROS 2 here: the middleware is the in-process bus.
# --verbose for setup.py's "rlbridge build:" lines (what was compiled, or why not), shown here.
# --prefix: only what this install adds, laid out as under /usr/local (scripts run
# /usr/local/bin/python3, the same in both stages).
RUN pip install --no-cache-dir ".[plot]" --prefix=/install --verbose > /tmp/pip.log 2>&1 \
    || { tail -n 40 /tmp/pip.log; exit 1; }; \
    grep "rlbridge build:" /tmp/pip.log; rm /tmp/pip.log


FROM python:3.11-slim

# iproute2 brings `tc`, used by the optional impaired-link service (profile "impaired");
# libsodium23 is the library rlbridge.wire._chacha links against.
# apt-get clean: the official image's apt config drops downloaded .debs, another base may not.
RUN apt-get update \
    && apt-get install -y --no-install-recommends iproute2 libsodium23 \
    && apt-get clean && rm -rf /var/lib/apt/lists/*

COPY --from=build /install /usr/local
ENV PYTHONUNBUFFERED=1
# The image's promise, checked where it runs: compiled value path, libsodium's cipher.
RUN rlbridge --version | tee /tmp/version \
    && grep -q "^value path: compiled (mypyc" /tmp/version \
    && grep -q "^sealing (ChaCha20-Poly1305): libsodium" /tmp/version \
    && rm /tmp/version
# No HEALTHCHECK here: what "healthy" means depends on the role, so docker-compose.yml gives
# the bridge service `rlbridge ping --port 7411` (exit 0 when the server answers).
EXPOSE 7411/tcp 7411/udp
CMD ["rlbridge", "demo", "--seconds", "5", "--no-plot"]

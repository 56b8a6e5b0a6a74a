"""The SDK: the ``Bridge`` facade, its channels and its session.

Layers, bottom up: :mod:`rlbridge.csp` (CSP primitives) <- ``client.channels`` (the bridge's
channels) <- ``client.session`` (the connection and its threads) <- ``client`` (``Bridge``) <-
:mod:`rlbridge.hrt`. Import public names from :mod:`rlbridge`.
"""

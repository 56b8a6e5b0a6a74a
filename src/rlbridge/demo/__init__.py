"""Demonstrations a newcomer runs first: values flowing through a real server."""

"""The bridge's channels: CSP channels whose other end is a topic on the middleware (incoming,
outgoing), with their pacing, value checks, fail-safes and health."""

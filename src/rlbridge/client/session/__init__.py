"""One session with a bridge server: the connection, its handshake and security, the send and
receive threads, reconnect, services, actions and parameters."""

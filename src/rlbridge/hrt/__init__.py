"""Hosting a hard-real-time loop: the coupling patterns of thesis chapter 5, isolated loop
processes, shared memory and the real-time environment."""

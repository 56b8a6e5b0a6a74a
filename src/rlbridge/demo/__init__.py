"""``rlbridge demo``: the thesis's pan-tilt camera (section 3.1), simulated, through a real bridge.

Embedded side: :mod:`.plant` (the simulated camera), :mod:`.control` and :mod:`.loop` (the
control law and state machine, time passed in), :mod:`.controller` (the 1 kHz HRT loop and the
50 Hz telemetry process on the SDK's processes, timer and channels).

Middleware side: :mod:`.vision` (30 Hz set-points), :mod:`.monitor` (what comes back),
:mod:`.metrics`, :mod:`.dashboard` and :mod:`.plot` (how it is shown).

Glue: :mod:`.topics` (names, types, diagnostics), :mod:`.sides` (what each side starts and
stops), :mod:`.run` (the roles ``all``, ``bridge``, ``controller``), :mod:`.cli` (the command).
"""

"""Exit statuses the services end with and the stack reads back (supervisord's ``exitcodes``, ``status``,
``summary``).

Why their own module: the stack's readers (:mod:`jitterguard.stack.status`, :mod:`~jitterguard.stack.summary`,
:mod:`~jitterguard.stack.supervisor`) need the numbers, not the service runtime; taken from
:mod:`.service`, they had imported Zenoh and pydantic with them (the monitor-watch and ``summary`` start without
either). :mod:`.service` still offers both names.
"""

from __future__ import annotations

EXIT_NO_PROGRESS = 70
"""Exit status of a service the watchdog stopped (EX_SOFTWARE): the supervisor restarts it."""
EXIT_BAD_INPUT = 65
"""Exit status of a program told to stop on bad input (EX_DATAERR: ``replay --on-error stop`` at an unreadable
frame): a deliberate stop that a supervisor must not restart — the same input would stop it again. The stack's
replay program lists it in supervisord's ``exitcodes`` (``autorestart=unexpected``); the systemd unit in
``RestartPreventExitStatus``."""

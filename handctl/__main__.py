"""``python -m handctl`` is the ``handctl`` command; ``entry`` is both's first line."""

import os
import signal
import sys

from handctl.stopsignals import (  # standard library only
    ENDING,
    drives_a_hand,
    ignore_stops,
    interrupt,
    interruption,
)


def _standard_descriptors() -> None:
    """Descriptors 0, 1 and 2 open, on /dev/null where they were closed (``handctl run ...
    >&-``): the first file opened then took descriptor 1, the MCAP log, and what was
    printed or what a child process wrote to its stdout went into the log, which ended
    up empty."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            devnull = os.open(os.devnull, os.O_RDWR)
            if devnull != fd:
                os.dup2(devnull, fd)
                os.close(devnull)


def _load_orjson() -> None:
    """orjson loaded with the stop signals held back: its module set-up does not check the
    imports it makes, and an interrupt raised inside one (a Ctrl-C in the first half second
    of any command that reads JSON) crashed the process (SIGSEGV). Held back, the signal
    comes right after, as the interrupt it is."""
    held = {signal.SIGINT, signal.SIGTERM, signal.SIGTSTP, *ENDING}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        import orjson  # noqa: F401  # loaded here for the reason above
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def entry() -> int:
    """``handctl.cli.main``, with a signal that ends a command ending it from the first line.

    ``main`` takes the signals over once ``handctl.cli`` is loaded, some tens of milliseconds
    in; until then a Ctrl-C was Python's own (a ``KeyboardInterrupt`` traceback, and an exit
    by SIGINT) and a SIGTERM or SIGHUP killed the process. Nothing has started yet: it is the
    one line and exit 130 of any interrupt. Raising here is safe: ``handctl.cli`` loads
    neither extension modules nor code that ``exec`` compiles (``handctl.stopsignals``).
    """
    # SIGINT too, even if this process was started with it ignored (a script's background
    # job is): ``handctl run`` and ``handctl sim`` honour it as a stop whatever they
    # inherited, and a signal asked for is one from the first line on as well
    _standard_descriptors()  # sys.stdout and sys.stderr stay None if they were closed
    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    # SIGHUP, SIGQUIT (Ctrl-\\), SIGUSR1/2, SIGALRM, SIGXCPU and the rest of ENDING end a
    # command as Ctrl-C does, not by the signal (a run killed so in its first tenth of a
    # second, rc -10); unless started with them ignored (nohup: asked to go on)
    for sig in ENDING:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, interrupt)
    if drives_a_hand(sys.argv[1:]):  # Ctrl-Z as well (``stopsignals.DRIVING`` says why)
        signal.signal(signal.SIGTSTP, interrupt)
    try:
        _load_orjson()
        from handctl.cli import leave, main

        code = main()
    except KeyboardInterrupt:
        _quiet()
        print(f"handctl: {interruption()}", file=sys.stderr)
        return 130
    leave(code)
    return code


def _quiet() -> None:
    """``stopsignals.ignore_stops`` for an interrupted command, which never reached
    ``cli.leave``: one more SIGTERM of a burst killed it by the signal (exit 143) after it had
    said "interrupted". One landing while they are set is taken here, and they are set
    again."""
    while True:
        try:
            ignore_stops()
            return
        except KeyboardInterrupt:
            continue


if __name__ == "__main__":
    raise SystemExit(entry())

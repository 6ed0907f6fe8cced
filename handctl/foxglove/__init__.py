"""Foxglove views of a run: well-known-schema messages derived from the recorded numbers, and
the live WebSocket server that serves them while the hand runs or a log plays back."""

#: Where the live view listens: the loopback interface only, since a live view of a robot is
#: not for the network unless someone chooses to tunnel it. Here, not in ``live``, so that the
#: control process can name it without loading the Foxglove SDK: the server lives in the
#: writer process, and the loop's process has no part of it.
HOST = "127.0.0.1"


def check_port_free(port: int, option: str) -> None:
    """A ``ConfigError`` naming ``option`` when the live view could not listen on ``port``.

    Asked before anything starts: found out by the writer, it failed the run's start after the
    log had been opened (an existing file of that name emptied) and said only that the writer
    was gone; found out by a replay, it was the SDK's traceback. Bound the way the server
    binds (address reuse on, as listeners do), so that a port a finished run left in TIME_WAIT
    is not refused; what can still happen is another program taking the port in between."""
    import socket

    from handctl.errors import ConfigError

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((HOST, port))
        except OSError as exc:
            raise ConfigError(
                option, "", f"a port the live view can listen on at {HOST}", f"{port} ({exc})"
            ) from None

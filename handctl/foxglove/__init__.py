"""Foxglove views of a run: well-known-schema messages derived from the recorded numbers, and
the live WebSocket server that serves them while the hand runs or a log plays back."""

#: Where the live view listens: the loopback interface only, since a live view of a robot is
#: not for the network unless someone chooses to tunnel it. Here, not in ``live``, so that the
#: control process can name it without loading the Foxglove SDK: the server lives in the
#: writer process, and the loop's process has no part of it.
HOST = "127.0.0.1"

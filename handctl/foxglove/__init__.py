"""Foxglove views of a run: well-known-schema messages derived from the recorded numbers, and
the live WebSocket server that serves them while the hand runs or a log plays back."""

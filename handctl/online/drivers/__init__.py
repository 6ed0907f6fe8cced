"""Host-side drivers of the finger nodes: pure frame building and parsing, node state, hand map."""

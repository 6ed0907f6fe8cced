"""The online plane: what the control process runs every tick, and the bus it runs on.

Everything here does bounded work per tick and imports nothing but itself and the foundation
(errors, schema, config, protocol, busload, wirelimits, convention): never the analysis,
planning, the simulated hand, recording or a command (docs/architecture.md, "Import rules";
tests/unit/test_architecture.py checks it on this folder).
"""

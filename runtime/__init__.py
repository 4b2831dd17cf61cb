"""cmnav runtime: the flight program on the companion computer (never imports torch).

At the top: the flight loop and its parts (``flight``, ``policy_step``, ``watchdog``,
``command_gate``, ``slots``, ``timing``, ``tracking``), the adapters (``vehicle`` for MAVSDK,
``model`` for ONNX Runtime, ``camera/``), the shared data types (``state``), the config
(``config``, ``config_loader``) and the contract (``contract/``).  Grouped by role below it:
``log/`` (the MCAP flight log), ``service/`` (process plumbing), ``programs/`` (``cmnav fly``,
the SITL flight, ``cmnav replay``, the episode script, the safe stop) and ``faults/`` (test-only
fault injection).  See docs/architecture.md.
"""

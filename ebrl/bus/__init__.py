"""The bus: Zenoh session and asyncio bridge (:mod:`ebrl.bus.session`: ``Bus``, ``BusBase``, ``BusOptions``),
the in-memory bus for tests (:mod:`ebrl.bus.memory`), liveliness, sign-in. The key builders and the codec are a
layer below, beside the messages (:mod:`ebrl.keys`, :mod:`ebrl.codec`).

The package itself imports nothing, so importing one of its modules (``ebrl.bus.auth`` in the launcher) loads
only that module and what it imports, not the session."""

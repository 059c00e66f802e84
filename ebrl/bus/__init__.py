"""The bus: Zenoh session and asyncio bridge (:mod:`ebrl.bus.session`: ``Bus``, ``BusBase``, ``BusOptions``),
the in-memory bus for tests (:mod:`ebrl.bus.memory`), codec, key builders, liveliness, sign-in.

The package itself imports nothing: ``ebrl.messages`` imports ``ebrl.bus.codec`` and ``ebrl.bus.keys``, and
the session imports ``ebrl.messages``, so a package that loaded the session would be an import cycle."""

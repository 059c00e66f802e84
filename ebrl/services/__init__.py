"""The services: one module per role (sim, gen, train, eval, log, alloc, viz), each a thin adapter of the library
to the bus (subscribe, call ``ebrl.*``, publish), started by the launcher as ``python -m ebrl.services.<role>``."""

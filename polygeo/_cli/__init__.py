"""Sub-commands of the ``polygeo`` command line (one module each, registered as plug-ins)."""

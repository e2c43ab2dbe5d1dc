"""Polhemus Liberty magnetic tracker: protocol codec, driver and device emulator."""

"""An independent strapdown-unit emulator, written from docs/protocol.md alone (no gyrocal imports)."""

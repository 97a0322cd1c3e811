"""TI mmWave radar: data-port parser and chirp profiles (no I/O)."""

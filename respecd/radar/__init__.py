"""TI mmWave radar support: data-port parser (tlv, parser), chirp table and cfg text (chirp, cfg),
and the two serial ports' I/O helpers (cli_port, data_port) used by ``drivers/iwr6843.py``."""

"""coopd.daemon: the service around the mapping stages (config, control socket, systemd, checkpoints,
memory budget, thread priorities)."""

"""The simulated machine: drive cycles, the plant, sensor models and the inverter emulator."""

"""Real devices: the recorded-acquisition format, the TCP stream protocol, the device
emulator and the converter for other toolboxes' files (docs/device.md)."""

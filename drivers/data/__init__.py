"""Data shipped with the drivers: the drive EDS and the default bus configuration."""

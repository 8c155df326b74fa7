"""wristscan.drivers.sim."""

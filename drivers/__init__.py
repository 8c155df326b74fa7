"""wristscan.drivers."""

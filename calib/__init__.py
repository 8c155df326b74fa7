"""wristscan.calib."""

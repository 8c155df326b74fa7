"""wristscan.daemon."""

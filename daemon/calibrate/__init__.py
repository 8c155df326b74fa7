"""daemon/calibrate"""

"""daemon/scan"""

"""daemon/procedure"""

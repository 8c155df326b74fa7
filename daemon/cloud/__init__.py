"""daemon/cloud"""

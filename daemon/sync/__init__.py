"""daemon/sync"""

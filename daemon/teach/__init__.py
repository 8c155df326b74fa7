"""daemon/teach"""

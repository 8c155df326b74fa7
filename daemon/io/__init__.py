"""daemon/io"""

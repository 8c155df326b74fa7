"""daemon/simcell"""

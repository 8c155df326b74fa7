"""drivers/sim/ur"""

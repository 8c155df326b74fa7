"""drivers/ur"""

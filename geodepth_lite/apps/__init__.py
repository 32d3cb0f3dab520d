"""The apps wing: the commands a user runs on their own data or machine (predict, gpu-check, bundle).
"""

"""The training wing: the run config, the trainer and its command, several runs at once, checkpoints, the
cache of trained runs, inference, distributed set-up and each run's provenance.
"""

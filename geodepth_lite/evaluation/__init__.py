"""The evaluation wing: the seven metrics over a split, the trivial baselines, the border study, the
pre-registered ablation and its studies, the paper's tables, the gallery of real frames and external data.
"""

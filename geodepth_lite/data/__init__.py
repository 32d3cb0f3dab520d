"""The data wing: the procedural tube, its rendering to RGB and exact z-depth, the dataset manifest and its
checks, augmentation, the field-of-view mask, image and frame readers, and the public datasets' loaders.
"""

"""The workbook wing: what serves the notebooks and a class (the notebook set-up, widgets, reproduce, the
graded exercises and the course, the lesson guard, the web book, reviews and the sandbox).
"""

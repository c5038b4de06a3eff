"""Study mode: many people teach agents over the web, one ``train.py`` run each (``study.py``).

``layout`` (the study directory's files) imports only the standard library, so that ``evaluate.py`` can
read a study.
"""

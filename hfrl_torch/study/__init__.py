"""Study mode: many participants teach over the web, each in their own ``train.py`` run (issue 44)."""

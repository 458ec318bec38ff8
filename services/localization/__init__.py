"""Localization: the stages a query goes through (decode, extract, retrieve, match,
estimate-and-verify, answer, under one clock and budget) and the localizers that compose them:
one frame (``localizer``), several with their AR-session poses (``frames``), several
estimators on the same matches (``compare``)."""

"""Finger estimators: one module per method, one shared interface (``base.FingerEstimator``).

``REGISTRY`` maps the command-line names to the classes; ``make_estimator`` builds one.
"""

"""Finger estimators: one module per method, one shared interface (``base.FingerEstimator``).

``registry``: ``REGISTRY`` maps the command-line names to the classes, ``EstimatorSpec`` is a validated
choice of one, ``make_estimator`` builds it for a finger.
"""

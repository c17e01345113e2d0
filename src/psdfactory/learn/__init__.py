"""Learning from the manifests: data, models, training, evaluation, metrics, and the
device/precision/checkpoint helpers (``runtime``) that evaluation and deployment share."""

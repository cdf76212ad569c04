"""Forward network models: the numpy MLP and its file (`mlp`), the torch LM trainer (`train`)."""

from mrrig.model.mlp import MLP, ModelError, data_fingerprint

__all__ = ["MLP", "ModelError", "data_fingerprint"]

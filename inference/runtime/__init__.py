"""The live pipeline: ONNX Runtime and numpy only. Nothing under this package imports torch.

`pipeline` opens an exported model and renders novel views; `preprocess` turns frames and calibrated
cameras into model inputs; `synthetic` makes deterministic stand-in inputs for checks and benchmarks;
`metadata` reads a model file's metadata (its precision) before a session is opened.
"""
from inference.runtime.pipeline import (
                                        PREFERRED_PROVIDERS,
                                        ModelInfo,
                                        NovelView,
                                        NovelViewPipeline,
                                        available_providers,
                                        model_precision,
                                        open_session,
                                        provider_options,
                                        read_model_info,
)

__all__ = ["PREFERRED_PROVIDERS", "ModelInfo", "NovelView", "NovelViewPipeline", "available_providers",
           "model_precision", "open_session", "provider_options", "read_model_info"]

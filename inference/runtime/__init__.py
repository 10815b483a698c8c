"""The live pipeline: ONNX Runtime and numpy only. Nothing under this package imports torch.

`pipeline` opens an exported model and renders novel views; `preprocess` turns frames and calibrated
cameras into model inputs; `synthetic` makes deterministic stand-in inputs for checks and benchmarks;
`metadata` reads a model file's metadata (its precision) before a session is opened; `split` runs
the exported model as its two parts (stage 1 once per frame set, the view once per viewpoint).
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
from inference.runtime.split import SplitPipeline, part_path

__all__ = ["PREFERRED_PROVIDERS", "ModelInfo", "NovelView", "NovelViewPipeline", "SplitPipeline", "available_providers",
           "model_precision", "open_session", "part_path", "provider_options", "read_model_info"]

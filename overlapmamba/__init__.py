"""The ``overlapmamba`` command line: wiring only. Each command imports what it needs when
it runs, so ``overlapmamba --help`` starts fast and never imports torch or onnxruntime."""

__version__ = "0.1.0"

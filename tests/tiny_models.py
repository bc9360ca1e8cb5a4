"""Model sizes shared by the tests (importable from every test folder: tests/ holds the conftest)."""

# A DINOv3 ViT small enough to build and run in a test: transformers' DINOv3ViTConfig fields.
TINY_VIT = dict(
    hidden_size=32,
    intermediate_size=64,
    num_attention_heads=2,
    num_hidden_layers=2,
    num_register_tokens=2,
    patch_size=8,
)

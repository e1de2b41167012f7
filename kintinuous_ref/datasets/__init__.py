"""Reading and writing RGB-D sequences: TUM folders (tum) and generated scenes (synthetic)."""

"""scikit-learn's 8x8 digits (1797 images shipped inside the scikit-learn wheel; nothing is
downloaded) as the digits experiment (experiments/images/digits.py) and the UNet2D benchmark
(tests/bench/unet2d.py) use them: pixels 0..16 scaled to [-1, 1], items [1, 8, 8].
"""

import numpy as np


def load_digits_split(seed: int):
    """(x_train, x_test, y_train, y_test): a stratified 75/25 split by ``seed``."""
    from sklearn.datasets import load_digits
    from sklearn.model_selection import train_test_split

    d = load_digits()
    x = (d.images.astype(np.float32) / 8.0 - 1.0)[:, None, :, :]
    return train_test_split(x, d.target, test_size=0.25, stratify=d.target, random_state=seed)

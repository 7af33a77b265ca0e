import numpy as np

import relreward


def test_health_and_gradient(client, tiny):
    assert client.health() == "SERVING"
    x = np.zeros((2, tiny.horizon, tiny.transition_dim), np.float32)
    grad, rho = client.gradient(tiny.reward, x, t=3)
    assert grad.shape == x.shape and rho.shape == (2,)

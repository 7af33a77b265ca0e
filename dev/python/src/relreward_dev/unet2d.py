"""diffusers' own UNet2DModel and DDPMScheduler, configured as relreward's native Unet2d
(server/src/engine/nets/unet2d.rs) and its linear schedule: the independent reference that
tests/python/unet2d_reference.py drives for server/tests/unet2d_vs_diffusers.rs and that
tests/bench/unet2d.py times.

Module map: ``float64_tables`` (a diffusers scheduler's tables recomputed in float64, as
relreward derives its own, for step-by-step replays), ``build`` (a UNet2DModel from the config relreward's manifest carries; a
conditional one, ``config["conditioning"]`` = relreward's manifest conditioning, takes
``num_class_embeds`` for labels or ``class_embed_type="identity"`` for embeddings),
``scheduler`` (DDPM linear betas 1e-4 to 0.02 scaled by 1000 / T).
"""

from diffusers import DDPMScheduler, UNet2DModel

def build(config):
    levels = len(config["block_out_channels"])
    attention = config["attention"]
    down = ["DownBlock2D"] * (levels - 1) + ["AttnDownBlock2D" if attention else "DownBlock2D"]
    up = ["AttnUpBlock2D" if attention else "UpBlock2D"] + ["UpBlock2D"] * (levels - 1)
    return UNet2DModel(
        sample_size=(config["height"], config["width"]),
        in_channels=config["channels"],
        out_channels=config["channels"],
        block_out_channels=tuple(config["block_out_channels"]),
        layers_per_block=config["layers_per_block"],
        down_block_types=tuple(down),
        up_block_types=tuple(up),
        norm_num_groups=config["norm_num_groups"],
        attention_head_dim=config["attention_head_dim"],
        add_attention=attention,
        **class_embedding(config.get("conditioning")),
    )


def class_embedding(conditioning):
    """UNet2DModel's keyword arguments for relreward's manifest `conditioning` (None: none)."""
    if conditioning is None:
        return {}
    if conditioning["kind"] == "labels":
        return {"num_class_embeds": conditioning["num_classes"]}
    return {"class_embed_type": "identity"}


def scheduler(n_timesteps):
    scale = 1000.0 / n_timesteps
    return DDPMScheduler(num_train_timesteps=n_timesteps, beta_schedule="linear",
                         beta_start=1e-4 * scale, beta_end=0.02 * scale)


def float64_tables(s):
    """The scheduler ``s`` with alphas_cumprod (and DDIM's final alpha) in float64 from its
    float32 betas: diffusers keeps them in float32, which loses digits in 1 - abar; relreward
    derives its tables in float64, so a replay that should agree to 1e-5 per step runs on
    float64 tables."""
    import torch
    from diffusers import DDIMScheduler

    s.betas = s.betas.double()
    s.alphas = 1.0 - s.betas
    s.alphas_cumprod = torch.cumprod(s.alphas, 0)
    s.one = torch.tensor(1.0, dtype=torch.float64)
    if isinstance(s, DDIMScheduler):
        s.final_alpha_cumprod = torch.tensor(1.0, dtype=torch.float64) if s.config.set_alpha_to_one \
            else s.alphas_cumprod[0]
    return s

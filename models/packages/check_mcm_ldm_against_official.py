#!/usr/bin/env python3
"""LOCAL cross-check, never in CI: pkg_mcm_ldm's four ONNX graphs against the official MCM-LDM
PyTorch modules.

Each official module (XingliangJin/MCM-LDM at 701cc96: MldDenoiser, MldVae encode/decode,
MotionCLIP's Encoder_TRANSFORMER) is built with torch's own random initialisation; its tensors
are then fed, in graph-construction order, into pkg_mcm_ldm's builders in place of the seeded
weights, and both are run on the same inputs (batch 2, lengths 50 and 38, so the masks count).
Needs torch and timm (e.g. python) and a checkout of the official repository;
nothing from it is copied here.

    git clone https://github.com/XingliangJin/MCM-LDM MCM-LDM
    python models/packages/check_mcm_ldm_against_official.py --official MCM-LDM
"""
import argparse
import sys
from pathlib import Path

ap = argparse.ArgumentParser()
ap.add_argument("--official", type=Path, required=True, help="checkout of XingliangJin/MCM-LDM")
args = ap.parse_args()
sys.path.insert(0, str(args.official))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402
import torch  # noqa: E402

import pkg_mcm_ldm as P  # noqa: E402

torch.manual_seed(0)

def run_onnx(b, name, ins, out_shape):
    model = P.finish(b, name, b.out, "y", [P.io(n, s, int64=(n == "t")) for n, s, _ in ins], out_shape, "x")
    sess = ort.InferenceSession(model.SerializeToString())
    return sess.run(None, {n: v for n, _, v in ins})[0]

class Queue:
    def __init__(self, tensors): self.q = [t.detach().numpy().astype(np.float32) for t in tensors]
    def install(self):
        q = self.q
        orig = P.M.const
        def const(self, base, arr, param=True):
            if param:
                w = q.pop(0)
                assert w.size == arr.size, (base, arr.shape, w.shape)
                arr = w.reshape(arr.shape)
            return orig(self, base, arr, param)
        P.M.const = const
        return orig

def lin(m):  # our Linear stores W as [cin, cout]
    return [m.weight.T, m.bias]

def mha(a, d):  # torch MultiheadAttention -> q, k, v, out linears
    W, B = a.in_proj_weight, a.in_proj_bias
    return [W[:d].T, B[:d], W[d:2*d].T, B[d:2*d], W[2*d:].T, B[2*d:], a.out_proj.weight.T, a.out_proj.bias]

def torch_layer(l, d):  # nn.TransformerEncoderLayer / DETR encoder layer (post-norm)
    return mha(l.self_attn, d) + [l.norm1.weight, l.norm1.bias] + lin(l.linear1) + lin(l.linear2) + [l.norm2.weight, l.norm2.bias]

def detr_dec_layer(l, d):
    return (mha(l.self_attn, d) + [l.norm1.weight, l.norm1.bias] + mha(l.multihead_attn, d) + [l.norm2.weight, l.norm2.bias]
            + lin(l.linear1) + lin(l.linear2) + [l.norm3.weight, l.norm3.bias])

def skip(enc, layer_fn, d):
    out = []
    for l in enc.input_blocks: out += layer_fn(l, d)
    out += layer_fn(enc.middle_block, d)
    for l, linear in zip(enc.output_blocks, enc.linear_blocks): out += lin(linear) + layer_fn(l, d)
    return out

def report(name, ours, ref):
    err = np.abs(ours - ref).max(); scale = np.abs(ref).max()
    print(f"{name}: max |onnx - official| = {err:.2e} (scale {scale:.2f})")

B, T, d = 2, 50, 256
lengths = [T, T - 12]
mask = np.zeros((B, T), np.float32); mask[0] = 1; mask[1, :T - 12] = 1

# --- denoiser
from mld.models.architectures.mld_denoiser import MldDenoiser
den = MldDenoiser(ablation=None, nfeats=263, latent_dim=[7, 256], ff_size=1024, num_layers=9, num_heads=4,
                  position_embedding="learned").eval()
for p in den.parameters():  # learned PE / tokens start at zero in torch: give them values
    if p.dim() >= 1: torch.nn.init.normal_(p, std=0.02) if p.abs().sum() == 0 else None
w = lin(den.time_embedding.linear_1) + lin(den.time_embedding.linear_2) + [den.IN.weight, den.IN.bias, den.pe_content.pe]
w += torch_layer(den.seqTransEncoder.layers[0], d) + lin(den.linear) + [den.query_pos.pe] + lin(den.emb_proj_st[1])
te = den.trans_Encoder
w += lin(te.emb_proj_st[1]) + [te.global_motion_token, te.pe.pe] + torch_layer(te.seqTransEncoder.layers[0], d) + torch_layer(te.seqTransEncoder.layers[1], d)
for blk in den.blocks:
    w += lin(blk.adaLN_modulation[1]) + lin(blk.adaLN_modulation_trans[1])
    w += [blk.attn.qkv.weight[:d].T, blk.attn.qkv.bias[:d], blk.attn.qkv.weight[d:2*d].T, blk.attn.qkv.bias[d:2*d],
          blk.attn.qkv.weight[2*d:].T, blk.attn.qkv.bias[2*d:], blk.attn.proj.weight.T, blk.attn.proj.bias]
    w += lin(blk.mlp.fc1) + lin(blk.mlp.fc2)
q = Queue(w); orig = q.install()
b = P.denoiser(P.SIZES["paper"], 0)
assert not q.q, f"{len(q.q)} official tensors unused"
P.M.const = orig
x = torch.randn(B, 7, d); c = torch.randn(B, 7, d); s = torch.randn(B, 512); tr = torch.randn(B, T, 3)
t = torch.tensor([37, 37])  # the official forward broadcasts one timestep
with torch.no_grad():
    ref = den(x, t, [c, s[:, None], tr], lengths=lengths)[0].numpy()
ours = run_onnx(b, "den", [("x_t", ["N", 7, d], x.numpy()), ("t", ["N"], t.numpy()), ("content", ["N", 7, d], c.numpy()),
                           ("trajectory", ["N", "T", 3], tr.numpy()), ("mask", ["N", "T"], mask), ("style", ["N", 512], s.numpy())],
                ["N", 7, d])
report("denoiser (paper widths, lengths 50 and 38)", ours, ref)

# --- VAE
from mld.models.architectures.mld_vae import MldVae
vae = MldVae(ablation=None, nfeats=263, latent_dim=[7, 256], ff_size=1024, num_layers=9, num_heads=4,
             arch="encoder_decoder", activation="gelu", position_embedding="learned").eval()
for p in vae.parameters():
    if p.abs().sum() == 0: torch.nn.init.normal_(p, std=0.02)
w = lin(vae.skel_embedding) + [vae.global_motion_token, vae.query_pos_encoder.pe] + skip(vae.encoder, torch_layer, d) + [vae.encoder.norm.weight, vae.encoder.norm.bias]
q = Queue(w); orig = q.install(); b = P.vae_encoder(P.SIZES["paper"], 0); assert not q.q; P.M.const = orig
feats = torch.randn(B, T, 263)
with torch.no_grad():
    _, dist = vae.encode(feats, lengths)
ref = dist.loc.permute(1, 0, 2).numpy()
ours = run_onnx(b, "enc", [("features", ["N", "T", 263], feats.numpy()), ("mask", ["N", "T"], mask)], ["N", 7, d])
report("vae_encoder mu (lengths 50 and 38)", ours, ref)
w = [vae.query_pos_decoder.pe] + skip(vae.decoder, detr_dec_layer, d) + [vae.decoder.norm.weight, vae.decoder.norm.bias] + lin(vae.final_layer)
q = Queue(w); orig = q.install(); b = P.vae_decoder(P.SIZES["paper"], 0); assert not q.q; P.M.const = orig
z = torch.randn(7, B, d)
with torch.no_grad():
    ref = vae.decode(z, lengths).numpy()
ours = run_onnx(b, "dec", [("latent", ["N", 7, d], z.permute(1, 0, 2).numpy()), ("mask", ["N", "T"], mask)], ["N", "T", 263])
report("vae_decoder (lengths 50 and 38)", ours, ref)

# --- MotionCLIP encoder
from mld.models.motionclip_263.models.architectures.transformer import Encoder_TRANSFORMER
enc = Encoder_TRANSFORMER("cvae", 263, 1, 60, 1, False, "xyz", False, False, latent_dim=512, ff_size=1024,
                          num_layers=9, num_heads=4, activation="gelu").eval()
w = lin(enc.skelEmbedding) + [enc.muQuery, enc.sigmaQuery] + skip(enc.encoder, torch_layer, 512) + [enc.encoder.norm.weight, enc.encoder.norm.bias]
q = Queue(w); orig = q.install(); b = P.style_encoder(P.SIZES["paper"], 0); assert not q.q; P.M.const = orig
sf = torch.randn(B, T, 263)
with torch.no_grad():
    ref = enc({"x": sf.permute(0, 2, 1)[:, :, None, :], "y": torch.zeros(B, dtype=torch.long),
               "mask": torch.tensor(mask > 0)})["mu"].numpy()
ours = run_onnx(b, "sty", [("features", ["N", "T", 263], sf.numpy()), ("mask", ["N", "T"], mask)], ["N", 512])
report("style_encoder (MotionCLIP mu, lengths 50 and 38)", ours, ref)

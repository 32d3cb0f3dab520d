"""DepthNet (Sec. 3.B): shapes, output range, input errors, torchvision resnet18 weight mapping."""


import pytest
import torch

from geodepth_lite.core import model as M


def torchvision_resnet18_shapes() -> dict[str, tuple]:
    """Names and shapes of torchvision's resnet18 state dict, written out from its definition."""
    shapes: dict[str, tuple] = {"conv1.weight": (64, 3, 7, 7)}

    def bn(prefix, c):
        for k in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{k}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    bn("bn1", 64)
    in_c = 64
    for layer, c in zip((1, 2, 3, 4), (64, 128, 256, 512)):
        for block in (0, 1):
            p = f"layer{layer}.{block}"
            shapes[f"{p}.conv1.weight"] = (c, in_c if block == 0 else c, 3, 3)
            bn(f"{p}.bn1", c)
            shapes[f"{p}.conv2.weight"] = (c, c, 3, 3)
            bn(f"{p}.bn2", c)
            if block == 0 and layer > 1:
                shapes[f"{p}.downsample.0.weight"] = (c, in_c, 1, 1)
                bn(f"{p}.downsample.1", c)
        in_c = c
    shapes["fc.weight"] = (1000, 512)
    shapes["fc.bias"] = (1000,)
    return shapes

def synthetic_state_dict(seed=0):
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, s in torchvision_resnet18_shapes().items():
        sd[k] = torch.tensor(7) if k.endswith("num_batches_tracked") else torch.randn(s, generator=g)
    return sd

def test_output_shape_and_range():
    net = M.DepthNet().eval()
    x = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        d = net(x)
    assert d.shape == (2, 1, 64, 96)
    assert torch.all(d > M.MIN_DEPTH) and torch.all(d < M.MAX_DEPTH)

def test_backward_reaches_every_parameter():
    net = M.DepthNet()
    net(torch.rand(2, 3, 32, 32)).mean().backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None]
    assert not missing

def test_sigmoid_to_depth_is_log_uniform():
    s = torch.tensor([0.0, 0.5, 1.0])
    d = M.sigmoid_to_depth(s)
    assert torch.allclose(d, torch.tensor([0.01, 1.0, 100.0]), rtol=1e-5)
    assert torch.allclose(M.depth_to_sigmoid(d), s, atol=1e-6)

@pytest.mark.parametrize("shape", [(1, 3, 33, 64), (1, 3, 64, 100), (1, 1, 64, 64), (3, 64, 64)])
def test_bad_input_shape_is_a_clear_error(shape):
    with pytest.raises(ValueError, match="multiples of 32|B x 3 x H x W"):
        M.DepthNet()(torch.rand(*shape))

def test_feature_shapes_and_parameter_table():
    net = M.DepthNet()
    shapes = M.feature_shapes(net, 64, 128)
    assert shapes["encoder"] == [(64, 32, 64), (64, 16, 32), (128, 8, 16), (256, 4, 8), (512, 2, 4)]
    assert shapes["decoder"] == [(256, 4, 8), (128, 8, 16), (64, 16, 32), (32, 32, 64), (16, 64, 128)]
    assert shapes["output"] == [(1, 64, 128)]
    assert net.training  # mode restored
    table = dict(M.parameter_table(net))
    # torchvision resnet18 has 11,689,512 parameters, 513,000 of them in fc
    assert table["encoder (ResNet18, no fc)"] == 11_689_512 - 513_000
    assert table["spatial attention block"] == 2 * 7 * 7
    assert table["total"] == sum(v for k, v in table.items() if k != "total")

def test_encoder_has_torchvision_names_and_shapes():
    own = {k: tuple(v.shape) for k, v in M.ResNet18Encoder().state_dict().items()}
    ref = {k: v for k, v in torchvision_resnet18_shapes().items() if not k.startswith("fc.")}
    assert own == ref

def test_load_encoder_weights_from_file(tmp_path):
    sd = synthetic_state_dict()
    path = tmp_path / "resnet18.pth"
    torch.save(sd, path)
    net = M.DepthNet(encoder_weights=path)
    for k, v in net.encoder.state_dict().items():
        assert torch.equal(v, sd[k]), k
    # wrapped and DataParallel-prefixed files load too
    torch.save({"state_dict": {"module." + k: v for k, v in sd.items()}}, path)
    net2 = M.DepthNet(encoder_weights=path)
    assert torch.equal(net2.encoder.layer4[1].bn2.running_var, sd["layer4.1.bn2.running_var"])

def test_load_encoder_weights_errors(tmp_path):
    enc = M.ResNet18Encoder()
    sd = synthetic_state_dict()
    del sd["layer3.0.downsample.0.weight"]
    with pytest.raises(ValueError, match="missing 1 .*layer3.0.downsample.0.weight"):
        M.load_encoder_weights(enc, sd)
    sd = synthetic_state_dict()
    sd["layer2.0.conv1.weight"] = torch.zeros(128, 64, 5, 5)
    with pytest.raises(ValueError, match=r"layer2.0.conv1.weight has shape \(128, 64, 5, 5\)"):
        M.load_encoder_weights(enc, sd)
    sd = synthetic_state_dict()
    sd["layer5.0.conv1.weight"] = torch.zeros(1)
    with pytest.raises(ValueError, match="unexpected 1 .*layer5.0.conv1.weight"):
        M.load_encoder_weights(enc, sd)
    with pytest.raises(FileNotFoundError):
        M.DepthNet(encoder_weights=tmp_path / "nope.pth")
    bad = tmp_path / "bad.pth"
    bad.write_text("not a state dict")
    with pytest.raises(ValueError, match="cannot read"):
        M.DepthNet(encoder_weights=bad)

def test_spatial_attention_gates_with_pooled_maps():
    sab = M.SpatialAttention()
    with torch.no_grad():
        sab.conv.weight.zero_()
        sab.conv.weight[0, 0, 3, 3] = 1.0  # mean channel, centre tap
    x = torch.randn(1, 4, 5, 5)
    expected = x * torch.sigmoid(x.mean(1, keepdim=True))
    assert torch.allclose(sab(x), expected, atol=1e-6)
    with torch.no_grad():
        sab.conv.weight.zero_()
        sab.conv.weight[0, 1, 3, 3] = 1.0  # max channel
    assert torch.allclose(sab(x), x * torch.sigmoid(x.amax(1, keepdim=True)), atol=1e-6)


def test_replicate_padding_extends_the_edge_not_a_dark_frame():
    """padding="replicate": a padded convolution equals an unpadded one on the edge-replicated input."""
    import torch.nn.functional as F

    torch.manual_seed(0)
    net = M.DepthNet(padding="replicate")
    conv = net.decoder.head
    x = torch.rand(1, conv.in_channels, 8, 8)
    ref = F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), conv.weight, conv.bias)
    torch.testing.assert_close(conv(x), ref)
    zeros = M.DepthNet(padding="zeros")
    zeros.load_state_dict(net.state_dict())  # same parameters: padding is not a weight
    img = torch.rand(1, 3, 64, 64)
    net.eval(), zeros.eval()
    with torch.no_grad():
        assert not torch.allclose(net(img), zeros(img))
        # a uniform image is seen as uniform up to the border with replicate padding, not with zeros
        flat = torch.full((1, 3, 64, 64), 0.5)
        rep, zer = net(flat)[0, 0], zeros(flat)[0, 0]
        assert float(rep.std()) < float(zer.std())
    with pytest.raises(ValueError, match="padding"):
        M.DepthNet(padding="mirror")


def test_input_pad_runs_on_the_mirrored_frame_and_crops_back():
    """input_pad=16: the depth equals the unpadded network's depth of the image mirrored by 16 px
    on every side (built here by index, the edge row not repeated), cropped to the image."""
    torch.manual_seed(0)
    padded = M.DepthNet(input_pad=16).eval()
    plain = M.DepthNet().eval()
    plain.load_state_dict(padded.state_dict())  # the pad is not a weight
    img = torch.rand(2, 3, 32, 64)

    def mirrored(n):  # source index of each padded position: 16..1, 0..n-1, n-2..n-17
        return torch.cat((torch.arange(16, 0, -1), torch.arange(n), torch.arange(n - 2, n - 18, -1)))

    frame = img.index_select(-2, mirrored(32)).index_select(-1, mirrored(64))
    assert frame.shape[-2:] == (64, 96)
    with torch.no_grad():
        d = padded(img)
        torch.testing.assert_close(d, plain(frame)[..., 16:48, 16:80])
        assert d.shape == (2, 1, 32, 64)
        assert not torch.allclose(d, plain(img))  # the border now sees mirrored image, not zeros
    for bad in (-16, 8, 1.5, True):
        with pytest.raises(ValueError, match="input_pad"):
            M.DepthNet(input_pad=bad)
    with pytest.raises(ValueError, match="input_pad 32 needs an image larger"):
        M.DepthNet(input_pad=32)(torch.rand(1, 3, 32, 64))

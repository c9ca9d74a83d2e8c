import json
from pathlib import Path

import pytest
import torch

from occflownet.model.backbone import ResNet, load_torchvision_state_dict, load_torchvision_weights

# key -> shape of torchvision 0.28's resnet18()/resnet50() state dicts (generated from torchvision's resnet.py)
TV = json.loads((Path(__file__).parent / "data" / "torchvision_resnet_keys.json").read_text())


@pytest.mark.parametrize("name,args", [("resnet18", ("basic", (2, 2, 2, 2), 64)),
                                       ("resnet50", ("bottleneck", (3, 4, 6, 3), 64))])
def test_parameter_names_and_shapes_match_torchvision(name, args):
    own = {k: list(v.shape) for k, v in ResNet(*args).state_dict().items()}
    expected = {k: v for k, v in TV[name].items() if not k.startswith("fc.")}
    assert own == expected


def _fake_torchvision_state(name):
    g = torch.Generator().manual_seed(0)
    return {k: (torch.randint(0, 5, shape, generator=g) if k.endswith("num_batches_tracked")
                else torch.randn(shape, generator=g)) for k, shape in TV[name].items()}


def test_loads_a_torchvision_weight_file(tmp_path):
    sd = _fake_torchvision_state("resnet18")          # includes fc.weight / fc.bias, which are ignored
    path = tmp_path / "resnet18.pth"
    torch.save(sd, path)
    net = ResNet("basic", (2, 2, 2, 2), 64)
    load_torchvision_weights(net, path)
    for k, v in net.state_dict().items():
        assert torch.equal(v, sd[k]), k              # exact: the loaded weights are copies of the file's


def test_wrong_weights_are_rejected_with_the_file_name(tmp_path):
    net = ResNet("bottleneck", (3, 4, 6, 3), 64)
    path = tmp_path / "r18.pth"
    torch.save(_fake_torchvision_state("resnet18"), path)
    with pytest.raises(ValueError, match="r18.pth"):
        load_torchvision_weights(net, path)
    bad = tmp_path / "garbage.pth"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="garbage.pth"):
        load_torchvision_weights(net, bad)
    sd = _fake_torchvision_state("resnet50")
    sd["conv1.weight"] = torch.zeros(64, 3, 3, 3)
    with pytest.raises(ValueError, match="shape mismatch"):
        load_torchvision_state_dict(net, sd)


def test_feature_strides():
    net = ResNet("basic", (1, 1, 1, 1), 8).eval()
    c3, c4 = net(torch.zeros(2, 3, 64, 96))
    assert c3.shape == (2, 32, 4, 6) and c4.shape == (2, 64, 2, 3)
    assert net.out_channels == (32, 64)

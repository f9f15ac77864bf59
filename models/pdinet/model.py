"""PDI-Net: U-Net reconstruction + semi-U-Net shared encoder + PALS-Bridge + YOLO detector.

Follows the paper's Method section:
  * U-Net reconstruction module (ConvBlocks, encoder-decoder with skips, image output);
  * semi-U-Net = ConvBlocks 1-3, shared with the detector (Strategy 3), feature at 1/4 scale;
  * PALS-Bridge (Eq. pals-paths / pals-psf-gates / pals-fusion):
      s = SiLU(BN(grouped 3x3 conv(x)))
      l = BN_l(PW(DW_15x15(x)))
      lam = BN_lam(x * K_lap)              (fixed 3x3 Laplacian, depthwise)
      k = bilinear(psf_blur 6x8 -> HxW)     (align_corners=False = ONNX half_pixel)
      g_s = clip(sigmoid(th_s) + a_s (1-k)), g_l = clip(sigmoid(th_l) + a_l k),
      g_lam = clip(sigmoid(th_lam) + a_lam (1-k))
      y = BN_out(SE(x + eta (g_s s + g_l l + g_lam lam)))
  * YOLOv5s-style (C3, SPPF, PAN, 3 anchors/scale) or YOLOv8s-style (C2f, decoupled DFL head)
    detector fed at 1/4 scale by the bridge; in-graph decode as ultralytics exports do.

`width` scales every channel count; width=1.0 gives YOLOv5s/YOLOv8s detector widths and a
32-channel U-Net base (about 15 M parameters, a ~60 MB ONNX file).
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

NUM_CLASSES = 6  # M3FD: People, Car, Bus, Motorcycle, Lamp, Truck
GATE_THETA_INIT = (-3.0, -2.0, -4.0)  # (small, large, laplacian): conservative branch prior
ETA_INIT = 0.2
V5_ANCHORS = (
    (10, 13, 16, 30, 33, 23),
    (30, 61, 62, 45, 59, 119),
    (116, 90, 156, 198, 373, 326),
)
STRIDES = (8, 16, 32)


def ch(c, width, divisor=4):
    return max(divisor, int(math.ceil(c * width / divisor) * divisor))


# ---------------------------------------------------------------- U-Net / semi-U-Net
class ConvBlock(nn.Module):
    """(Conv3x3 -> BN -> ReLU) x 2, the U-Net building block."""

    def __init__(self, c1, c2):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(c1, c2, 3, 1, 1, bias=False), nn.BatchNorm2d(c2), nn.ReLU(inplace=True),
            nn.Conv2d(c2, c2, 3, 1, 1, bias=False), nn.BatchNorm2d(c2), nn.ReLU(inplace=True),
        )

    def forward(self, x):
        return self.body(x)


class UNet(nn.Module):
    """Encoder ConvBlocks 1-5, decoder with transposed-conv upsampling and skip concats."""

    def __init__(self, base, in_ch=1):
        super().__init__()
        c = [base, base * 2, base * 4, base * 8, base * 16]
        self.enc1 = ConvBlock(in_ch, c[0])
        self.enc2 = ConvBlock(c[0], c[1])
        self.enc3 = ConvBlock(c[1], c[2])
        self.enc4 = ConvBlock(c[2], c[3])
        self.enc5 = ConvBlock(c[3], c[4])
        self.up4 = nn.ConvTranspose2d(c[4], c[3], 2, 2)
        self.dec4 = ConvBlock(c[4], c[3])
        self.up3 = nn.ConvTranspose2d(c[3], c[2], 2, 2)
        self.dec3 = ConvBlock(c[3], c[2])
        self.up2 = nn.ConvTranspose2d(c[2], c[1], 2, 2)
        self.dec2 = ConvBlock(c[2], c[1])
        self.up1 = nn.ConvTranspose2d(c[1], c[0], 2, 2)
        self.dec1 = ConvBlock(c[1], c[0])
        self.out = nn.Conv2d(c[0], in_ch, 1)

    def semi(self, x):
        """The semi-U-Net: ConvBlocks 1-3 (Strategy 3); returns the skips and the 1/4 feature."""
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        e3 = self.enc3(F.max_pool2d(e2, 2))
        return e1, e2, e3

    def decode(self, x, e1, e2, e3):
        e4 = self.enc4(F.max_pool2d(e3, 2))
        e5 = self.enc5(F.max_pool2d(e4, 2))
        d4 = self.dec4(torch.cat([self.up4(e5), e4], 1))
        d3 = self.dec3(torch.cat([self.up3(d4), e3], 1))
        d2 = self.dec2(torch.cat([self.up2(d3), e2], 1))
        d1 = self.dec1(torch.cat([self.up1(d2), e1], 1))
        return x + self.out(d1)  # residual reconstruction of the clean frame


# ---------------------------------------------------------------- PALS-Bridge
class SE(nn.Module):
    def __init__(self, c, r=4):
        super().__init__()
        h = max(8, c // r)
        self.fc1 = nn.Conv2d(c, h, 1)
        self.fc2 = nn.Conv2d(h, c, 1)

    def forward(self, x):
        w = torch.sigmoid(self.fc2(F.relu(self.fc1(F.adaptive_avg_pool2d(x, 1)))))
        return x * w


def blur_at(psf_blur, size, window=None):
    """The blur map on a feature grid of `size`: bilinear over the whole frame, or, for crops
    (`window`: the frame's (H, W), the crop's (h, w) and each frame's (y, x) offset in pixels,
    multiples of the grid's stride), the frame's map at the grid's stride cut to each crop, so
    a crop sees the blur its pixels have in the whole frame."""
    if window is None:
        return F.interpolate(psf_blur, size=size, mode="bilinear", align_corners=False)
    (fh, fw), (h, w), offsets = window
    sy, sx = h // size[0], w // size[1]
    full = F.interpolate(psf_blur, size=(fh // sy, fw // sx), mode="bilinear", align_corners=False)
    return torch.stack([full[i, :, oy // sy:oy // sy + size[0], ox // sx:ox // sx + size[1]]
                        for i, (oy, ox) in enumerate(offsets)])


class PALSBridge(nn.Module):
    def __init__(self, c, groups=4, large_k=15):
        super().__init__()
        self.small = nn.Sequential(
            nn.Conv2d(c, c, 3, 1, 1, groups=groups, bias=False), nn.BatchNorm2d(c), nn.SiLU())
        self.dw = nn.Conv2d(c, c, large_k, 1, large_k // 2, groups=c, bias=False)
        self.pw = nn.Conv2d(c, c, 1, bias=False)
        self.bn_l = nn.BatchNorm2d(c)
        lap = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])
        self.register_buffer("lap", lap.view(1, 1, 3, 3))
        self.bn_lam = nn.BatchNorm2d(c)
        self.theta = nn.Parameter(torch.tensor(GATE_THETA_INIT))
        self.alpha = nn.Parameter(torch.full((3,), 0.5))
        self.eta = nn.Parameter(torch.tensor(ETA_INIT))
        self.se = SE(c)
        self.bn_out = nn.BatchNorm2d(c)

    def gates(self, k):
        gb = torch.sigmoid(self.theta)
        g_s = torch.clamp(gb[0] + self.alpha[0] * (1.0 - k), 0.0, 1.0)
        g_l = torch.clamp(gb[1] + self.alpha[1] * k, 0.0, 1.0)
        g_lam = torch.clamp(gb[2] + self.alpha[2] * (1.0 - k), 0.0, 1.0)
        return g_s, g_l, g_lam

    def forward(self, x, psf_blur, window=None):
        c = x.shape[1]
        s = self.small(x)
        l = self.bn_l(self.pw(self.dw(x)))
        lam = self.bn_lam(F.conv2d(x, self.lap.expand(c, 1, 3, 3), padding=1, groups=c))
        k = blur_at(psf_blur, x.shape[-2:], window)
        g_s, g_l, g_lam = self.gates(k)
        return self.bn_out(self.se(x + self.eta * (g_s * s + g_l * l + g_lam * lam)))


# ---------------------------------------------------------------- YOLO blocks
class Conv(nn.Module):
    """Conv -> BN -> SiLU (ultralytics Conv)."""

    def __init__(self, c1, c2, k=1, s=1, g=1):
        super().__init__()
        self.conv = nn.Conv2d(c1, c2, k, s, k // 2, groups=g, bias=False)
        self.bn = nn.BatchNorm2d(c2)
        self.act = nn.SiLU()

    def forward(self, x):
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    def __init__(self, c1, c2, shortcut=True, e=0.5):
        super().__init__()
        h = int(c2 * e)
        self.cv1 = Conv(c1, h, 1 if e == 0.5 and c1 != c2 else 3)
        self.cv2 = Conv(h, c2, 3)
        self.add = shortcut and c1 == c2

    def forward(self, x):
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C3(nn.Module):
    def __init__(self, c1, c2, n=1, shortcut=True):
        super().__init__()
        h = c2 // 2
        self.cv1, self.cv2, self.cv3 = Conv(c1, h), Conv(c1, h), Conv(2 * h, c2)
        self.m = nn.Sequential(*(Bottleneck(h, h, shortcut, e=1.0) for _ in range(n)))

    def forward(self, x):
        return self.cv3(torch.cat([self.m(self.cv1(x)), self.cv2(x)], 1))


class C2f(nn.Module):
    def __init__(self, c1, c2, n=1, shortcut=False):
        super().__init__()
        self.c = c2 // 2
        self.cv1 = Conv(c1, 2 * self.c)
        self.cv2 = Conv((2 + n) * self.c, c2)
        self.m = nn.ModuleList(Bottleneck(self.c, self.c, shortcut, e=1.0) for _ in range(n))

    def forward(self, x):
        y = list(self.cv1(x).split((self.c, self.c), 1))
        for m in self.m:
            y.append(m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    def __init__(self, c1, c2, k=5):
        super().__init__()
        h = c1 // 2
        self.cv1, self.cv2 = Conv(c1, h), Conv(4 * h, c2)
        self.k = k

    def forward(self, x):
        x = self.cv1(x)
        y1 = F.max_pool2d(x, self.k, 1, self.k // 2)
        y2 = F.max_pool2d(y1, self.k, 1, self.k // 2)
        y3 = F.max_pool2d(y2, self.k, 1, self.k // 2)
        return self.cv2(torch.cat([x, y1, y2, y3], 1))


class Backbone(nn.Module):
    """YOLO backbone from the 1/4-scale bridge feature to P3/8, P4/16, P5/32 (+SPPF)."""

    def __init__(self, c_in, widths, block, depths):
        super().__init__()
        c2, c3, c4, c5 = widths
        self.p2 = block(c_in, c2, depths[0], True)
        self.down3, self.p3 = Conv(c2, c3, 3, 2), block(c3, c3, depths[1], True)
        self.down4, self.p4 = Conv(c3, c4, 3, 2), block(c4, c4, depths[2], True)
        self.down5, self.p5 = Conv(c4, c5, 3, 2), block(c5, c5, depths[0], True)
        self.sppf = SPPF(c5, c5)

    def forward(self, x):
        x = self.p2(x)
        p3 = self.p3(self.down3(x))
        p4 = self.p4(self.down4(p3))
        p5 = self.sppf(self.p5(self.down5(p4)))
        return p3, p4, p5


class NeckV5(nn.Module):
    """YOLOv5 PAN: top-down with 1x1 lateral convs, then bottom-up."""

    def __init__(self, widths, n):
        super().__init__()
        _, c3, c4, c5 = widths
        self.lat5 = Conv(c5, c4)
        self.td4 = C3(2 * c4, c4, n, False)
        self.lat4 = Conv(c4, c3)
        self.td3 = C3(2 * c3, c3, n, False)
        self.bu3 = Conv(c3, c3, 3, 2)
        self.out4 = C3(2 * c3, c4, n, False)
        self.bu4 = Conv(c4, c4, 3, 2)
        self.out5 = C3(2 * c4, c5, n, False)

    def forward(self, p3, p4, p5):
        l5 = self.lat5(p5)
        t4 = self.td4(torch.cat([F.interpolate(l5, scale_factor=2.0, mode="nearest"), p4], 1))
        l4 = self.lat4(t4)
        o3 = self.td3(torch.cat([F.interpolate(l4, scale_factor=2.0, mode="nearest"), p3], 1))
        o4 = self.out4(torch.cat([self.bu3(o3), l4], 1))
        o5 = self.out5(torch.cat([self.bu4(o4), l5], 1))
        return o3, o4, o5


class NeckV8(nn.Module):
    """YOLOv8 PAN: no lateral convs, C2f without shortcuts."""

    def __init__(self, widths, n):
        super().__init__()
        _, c3, c4, c5 = widths
        self.td4 = C2f(c5 + c4, c4, n)
        self.td3 = C2f(c4 + c3, c3, n)
        self.bu3 = Conv(c3, c3, 3, 2)
        self.out4 = C2f(c3 + c4, c4, n)
        self.bu4 = Conv(c4, c4, 3, 2)
        self.out5 = C2f(c4 + c5, c5, n)

    def forward(self, p3, p4, p5):
        t4 = self.td4(torch.cat([F.interpolate(p5, scale_factor=2.0, mode="nearest"), p4], 1))
        o3 = self.td3(torch.cat([F.interpolate(t4, scale_factor=2.0, mode="nearest"), p3], 1))
        o4 = self.out4(torch.cat([self.bu3(o3), t4], 1))
        o5 = self.out5(torch.cat([self.bu4(o4), p5], 1))
        return o3, o4, o5


def make_grid(h, w, device=None):
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                            torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
    return xs, ys


class DetectV5(nn.Module):
    """YOLOv5 Detect with in-graph anchor decode -> [1, N, 5 + nc] (xywh, obj, cls)."""

    def __init__(self, chs, nc=NUM_CLASSES):
        super().__init__()
        self.nc, self.no, self.na = nc, nc + 5, 3
        self.m = nn.ModuleList(nn.Conv2d(c, self.na * self.no, 1) for c in chs)
        self.register_buffer("anchors", torch.tensor(V5_ANCHORS, dtype=torch.float32).view(3, 3, 2))
        for conv, s in zip(self.m, STRIDES):  # ultralytics' prior-probability bias init
            b = conv.bias.view(self.na, -1)
            b.data[:, 4] += math.log(8 / (640 / s) ** 2)
            b.data[:, 5:] += math.log(0.6 / (self.nc - 0.99999))

    def forward(self, feats):
        out = []
        for i, x in enumerate(feats):
            x = self.m[i](x)
            bs, _, ny, nx = x.shape
            x = x.view(bs, self.na, self.no, ny, nx).permute(0, 1, 3, 4, 2).contiguous()
            if self.training:  # raw maps for the loss: [bs, na, ny, nx, 5 + nc]
                out.append(x)
                continue
            gx, gy = make_grid(ny, nx, x.device)
            grid = torch.stack((gx, gy), 2).view(1, 1, ny, nx, 2) - 0.5
            anchor_grid = self.anchors[i].view(1, self.na, 1, 1, 2)
            xy, wh, conf = x.sigmoid().split((2, 2, self.nc + 1), 4)
            xy = (xy * 2 + grid) * STRIDES[i]
            wh = (wh * 2) ** 2 * anchor_grid
            out.append(torch.cat((xy, wh, conf), 4).view(bs, self.na * nx * ny, self.no))
        return out if self.training else torch.cat(out, 1)


class DFL(nn.Module):
    """Distribution focal loss integral: softmax over reg_max bins, then a fixed arange conv."""

    def __init__(self, c1=16):
        super().__init__()
        self.conv = nn.Conv2d(c1, 1, 1, bias=False).requires_grad_(False)
        self.conv.weight.data[:] = torch.arange(c1, dtype=torch.float32).view(1, c1, 1, 1)
        self.c1 = c1

    def forward(self, x):
        b, _, a = x.shape
        return self.conv(x.view(b, 4, self.c1, a).transpose(2, 1).softmax(1)).view(b, 4, a)


class DetectV8(nn.Module):
    """YOLOv8 decoupled head with DFL decode -> [1, 4 + nc, N] (xywh, class scores)."""

    def __init__(self, chs, nc=NUM_CLASSES, reg_max=16):
        super().__init__()
        self.nc, self.reg_max = nc, reg_max
        c2 = max(16, chs[0] // 4, reg_max * 4)
        c3 = max(chs[0], min(nc, 100))
        self.cv2 = nn.ModuleList(
            nn.Sequential(Conv(c, c2, 3), Conv(c2, c2, 3), nn.Conv2d(c2, 4 * reg_max, 1)) for c in chs)
        self.cv3 = nn.ModuleList(
            nn.Sequential(Conv(c, c3, 3), Conv(c3, c3, 3), nn.Conv2d(c3, nc, 1)) for c in chs)
        self.dfl = DFL(reg_max)
        for a, b, s in zip(self.cv2, self.cv3, STRIDES):  # ultralytics' bias init
            a[-1].bias.data[:] = 1.0
            b[-1].bias.data[: nc] = math.log(5 / nc / (640 / s) ** 2)

    def forward(self, feats):
        outs, anchors, strides = [], [], []
        for i, x in enumerate(feats):
            outs.append(torch.cat((self.cv2[i](x), self.cv3[i](x)), 1))
        if self.training:  # raw maps for the loss: [bs, 4 * reg_max + nc, ny, nx] per stride
            return outs
        for i, x in enumerate(feats):
            _, _, h, w = x.shape
            gx, gy = make_grid(h, w, x.device)
            anchors.append(torch.stack((gx + 0.5, gy + 0.5), -1).view(-1, 2))
            strides.append(torch.full((h * w, 1), float(STRIDES[i]), device=x.device))
        b = outs[0].shape[0]
        x = torch.cat([o.view(b, 4 * self.reg_max + self.nc, -1) for o in outs], 2)
        box, cls = x.split((4 * self.reg_max, self.nc), 1)
        anchor_points = torch.cat(anchors).transpose(0, 1).unsqueeze(0)
        stride_t = torch.cat(strides).transpose(0, 1).unsqueeze(0)
        lt, rb = self.dfl(box).chunk(2, 1)
        x1y1, x2y2 = anchor_points - lt, anchor_points + rb
        dbox = torch.cat(((x1y1 + x2y2) / 2, x2y2 - x1y1), 1) * stride_t
        return torch.cat((dbox, cls.sigmoid()), 1)


# ---------------------------------------------------------------- PDI-Net
class PDINet(nn.Module):
    def __init__(self, head="v5", width=1.0, depth=1.0, nc=NUM_CLASSES, psf_blur=None, in_ch=1):
        """psf_blur: None -> the blur map is a forward() input; else a [6, 8] tensor baked in.
        in_ch: image channels (3 for thermal frames stored as RGB, as FLIR ADAS's JPEGs are)."""
        super().__init__()
        base = ch(32, width)
        self.unet = UNet(base, in_ch)
        c_sh = base * 4  # enc3 output, 1/4 scale
        self.bridge = PALSBridge(c_sh)
        widths = (ch(64, width), ch(128, width), ch(256, width), ch(512, width))
        if head == "v5":
            n = (max(1, round(1 * depth)), max(1, round(2 * depth)), max(1, round(3 * depth)))
            self.backbone = Backbone(c_sh, widths, C3, n)
            self.neck = NeckV5(widths, n[0])
            self.detect = DetectV5(widths[1:], nc)
        elif head == "v8":
            n = (max(1, round(1 * depth)), max(1, round(2 * depth)), max(1, round(2 * depth)))
            self.backbone = Backbone(c_sh, widths, C2f, n)
            self.neck = NeckV8(widths, n[0])
            self.detect = DetectV8(widths[1:], nc)
        else:
            raise ValueError(f"unknown head {head!r} (expected v5 or v8)")
        self.head = head
        if psf_blur is not None:
            self.register_buffer("psf_blur", torch.as_tensor(psf_blur, dtype=torch.float32).view(1, 1, 6, 8))
        else:
            self.psf_blur = None

    def forward(self, image, psf_blur=None, window=None):
        """window: for training on crops, where each image sits in its frame (see `blur_at`)."""
        if psf_blur is None:
            psf_blur = self.psf_blur
        e1, e2, e3 = self.unet.semi(image)
        recon = self.unet.decode(image, e1, e2, e3)
        det = self.detect(self.neck(*self.backbone(self.bridge(e3, psf_blur, window))))
        return recon, det


class PlainDetector(nn.Module):
    """Not PDI-Net: a YOLO detector on the raw frame (strided stem, no reconstruction branch,
    no PSF gating), for checking what the toolchain does with a model it was not built for."""

    def __init__(self, head="v5", width=1.0, nc=NUM_CLASSES, in_ch=1):
        super().__init__()
        c_stem = ch(64, width)
        widths = (ch(64, width), ch(128, width), ch(256, width), ch(512, width))
        self.stem = nn.Sequential(Conv(in_ch, c_stem // 2, 3, 2), Conv(c_stem // 2, c_stem, 3, 2))
        block = C3 if head == "v5" else C2f
        self.backbone = Backbone(c_stem, widths, block, (1, 1, 1))
        self.neck = NeckV5(widths, 1) if head == "v5" else NeckV8(widths, 1)
        self.detect = DetectV5(widths[1:], nc) if head == "v5" else DetectV8(widths[1:], nc)

    def forward(self, image):
        return self.detect(self.neck(*self.backbone(self.stem(image))))

"""YOLOv5 detection loss: anchor-ratio assignment with neighbour cells, CIoU boxes, BCE
objectness (IoU targets, per-scale balance) and classes.

  L_det = 0.05 L_box + 1.0 L_obj + 0.5 L_cls  (ultralytics' YOLOv5 hyperparameters)
"""
import torch
import torch.nn.functional as F

from pdinet.boxes import ciou_xywh
from pdinet.model import STRIDES

HYP = dict(box=0.05, obj=1.0, cls=0.5, anchor_t=4.0)
OBJ_BALANCE = (4.0, 1.0, 0.4)  # P3, P4, P5 (ultralytics)
PARTS = ("l_box", "l_obj", "l_cls")


def yolo_v5_loss(preds, targets, anchors, nc):
    """preds: list of [bs, na, ny, nx, 5+nc]; targets: [n, 6] (img, cls, cx, cy, w, h) normalized."""
    dev = preds[0].device
    lbox, lobj, lcls = torch.zeros(1, device=dev), torch.zeros(1, device=dev), torch.zeros(1, device=dev)
    g = 0.5
    off = torch.tensor([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], device=dev).float() * g
    na = anchors.shape[1]
    for i, p in enumerate(preds):
        bs, _, ny, nx, _ = p.shape
        anc = anchors[i] / STRIDES[i]  # anchors in grid units
        tobj = torch.zeros(p.shape[:4], device=dev)
        if targets.shape[0]:
            gain = torch.tensor([1, 1, nx, ny, nx, ny], device=dev).float()
            t = targets * gain  # to grid units
            t = t[None].repeat(na, 1, 1)  # [na, n, 6]
            ai = torch.arange(na, device=dev).float().view(na, 1).repeat(1, targets.shape[0])
            r = t[..., 4:6] / anc[:, None]
            j = torch.max(r, 1 / r).max(2)[0] < HYP["anchor_t"]
            t, ai = t[j], ai[j]
            gxy = t[:, 2:4]
            gxi = torch.tensor([nx, ny], device=dev) - gxy
            jx, ky = ((gxy % 1 < g) & (gxy > 1)).T
            lx, my = ((gxi % 1 < g) & (gxi > 1)).T
            sel = torch.stack((torch.ones_like(jx), jx, ky, lx, my))
            t = t.repeat((5, 1, 1))[sel]
            ai = ai.repeat((5, 1))[sel]
            offsets = (torch.zeros_like(gxy)[None] + off[:, None])[sel]
            b, c = t[:, 0].long(), t[:, 1].long()
            gxy = t[:, 2:4]
            gij = (gxy - offsets).long()
            gi, gj = gij[:, 0].clamp(0, nx - 1), gij[:, 1].clamp(0, ny - 1)
            a = ai.long()
            ps = p[b, a, gj, gi]
            if ps.shape[0]:
                pxy = ps[:, :2].sigmoid() * 2 - 0.5
                pwh = (ps[:, 2:4].sigmoid() * 2) ** 2 * anc[a]
                tbox = torch.cat((gxy - gij.float(), t[:, 4:6]), 1)
                iou = ciou_xywh(torch.cat((pxy, pwh), 1), tbox)
                lbox += (1.0 - iou).mean()
                tobj[b, a, gj, gi] = iou.detach().clamp(0).type(tobj.dtype)
                tc = torch.zeros_like(ps[:, 5:])
                tc[range(ps.shape[0]), c] = 1.0
                lcls += F.binary_cross_entropy_with_logits(ps[:, 5:], tc)
        lobj += F.binary_cross_entropy_with_logits(p[..., 4], tobj) * OBJ_BALANCE[i]
    bs = preds[0].shape[0]
    return (HYP["box"] * lbox + HYP["obj"] * lobj + HYP["cls"] * lcls) * bs, torch.cat((lbox, lobj, lcls)).detach()

"""Box geometry for the losses: corner form and complete IoU."""
import math

import torch


def xywh_to_xyxy(b):
    return torch.cat((b[..., :2] - b[..., 2:] / 2, b[..., :2] + b[..., 2:] / 2), -1)


def ciou_xyxy(b1, b2, eps=1e-7):
    """Complete IoU of corner-form boxes (last axis 4), broadcast over the leading axes."""
    (ax1, ay1, ax2, ay2), (bx1, by1, bx2, by2) = b1.unbind(-1), b2.unbind(-1)
    w1, h1, w2, h2 = ax2 - ax1, ay2 - ay1 + eps, bx2 - bx1, by2 - by1 + eps
    inter = (torch.min(ax2, bx2) - torch.max(ax1, bx1)).clamp(0) * (torch.min(ay2, by2) - torch.max(ay1, by1)).clamp(0)
    iou = inter / (w1 * h1 + w2 * h2 - inter + eps)
    cw = torch.max(ax2, bx2) - torch.min(ax1, bx1)
    chh = torch.max(ay2, by2) - torch.min(ay1, by1)
    c2 = cw ** 2 + chh ** 2 + eps
    rho2 = ((bx1 + bx2 - ax1 - ax2) ** 2 + (by1 + by2 - ay1 - ay2) ** 2) / 4
    v = (4 / math.pi ** 2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


def ciou_xywh(b1, b2):
    return ciou_xyxy(xywh_to_xyxy(b1), xywh_to_xyxy(b2))

"""What a client needs to shape itself: who its key is (`/me`) and the writable parameters."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api.auth import Principal
from app.api.deps import viewer
from app.api.responses import JsonResponse
from app.api.schemas import errors
from app.protocol.params import PARAMETERS

router = APIRouter(tags=["session"], responses=errors(401))


@router.get("/me", summary="The calling key: id, name and role (a client hides what it cannot do)")
async def me(principal: Principal = Depends(viewer)) -> JsonResponse:  # noqa: B008
    return JsonResponse(
        {"key_id": principal.key_id, "name": principal.name, "role": principal.role}
    )


@router.get(
    "/parameters",
    summary="Writable parameters with the manuals' ranges, units and the series that take them",
    dependencies=[Depends(viewer)],
)
async def parameters() -> JsonResponse:
    return JsonResponse(
        {
            "parameters": [
                {
                    "name": p.name,
                    "index": p.index,
                    "series": sorted(p.series),
                    "unit": p.unit,
                    "minimum": p.minimum,
                    "maximum": p.maximum,
                    "resolution": p.resolution,
                    "description": p.description,
                }
                for p in sorted(PARAMETERS.values(), key=lambda p: (p.index, p.name))
            ]
        }
    )

"""What a client needs to shape itself: who its key is (`/me`) and the writable parameters."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from eqgw.protocol.params import PARAMETERS
from eqgw.security.auth import Viewer, viewer
from eqgw.security.schemas import Me, ParameterList
from eqgw.security.sessions import who_json
from eqgw.web.responses import JsonResponse
from eqgw.web.schemas import errors

router = APIRouter(tags=["session"], responses=errors(401))


@router.get(
    "/me",
    summary="The calling key: id, name, role, scope (null: the whole fleet) and expiry "
    "(a client hides what it cannot do)",
    response_model=Me,
)
async def me(principal: Viewer) -> JsonResponse:
    return JsonResponse({**who_json(principal), "ends_at": principal.ends_at})


@router.get(
    "/parameters",
    summary="Writable parameters with the manuals' ranges, units and the series that take them",
    dependencies=[Depends(viewer)],
    response_model=ParameterList,
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
